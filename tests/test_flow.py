"""Tests of torchrl_ftb.flow (FlowToBetter, Alg. 4) and torchrl_ftb.analysis."""
from __future__ import annotations

import functools
import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_ftb.analysis import dynamics_error, improvement, novelty, plot_flow_curves, plot_histograms, toy_oracle_step
from torchrl_ftb.data.labels import make_scripted_labels, make_teacher, true_return
from torchrl_ftb.flow import (
    FlowToBetter,
    adaptive_flow_steps,
    improves,
    masked_true_return,
    masked_true_returns,
    normalized_scores,
    trajectory_validity,
    true_return_score,
)
from torchrl_ftb.preference import NORMALIZED_SCORE_KEY, ScoreModel
from torchrl_ftb.testing import make_toy_dataset, toy_reward

pytestmark = pytest.mark.usefixtures("one_thread")

H = 16


def _sum_ax(td):
    """A stand-in score: sum of x-actions over valid steps (the toy reward's main term)."""
    return (td["action"][..., 0] * td["mask"]).sum(-1)


def _shift_sampler(delta: float = 0.3, *, corrupt: str | None = None):
    """A stand-in sampler: returns the condition with x-actions pushed up by ``delta``."""

    def better(cond):
        out = cond.select("observation", "action", "mask").clone()
        m = out["mask"][..., None]
        act = out["action"].clone()
        act[..., 0] = (act[..., 0] + delta).clamp(-1, 1)
        if corrupt == "nan":
            act[0, 0, 0] = float("nan")
        elif corrupt == "big_action":
            act[..., 1] = 3.0
        elif corrupt == "short":
            out["mask"][:, 2:] = False
            m = out["mask"][..., None]
        out["action"] = act * m
        return out

    return TensorDictModule(better, ["condition"], ["sample"])


def test_normalized_improvement_is_meaningful_for_negative_scores():
    # raw scores all negative: the paper's raw ratio s_new / s_old > 1.1 would *reject* an
    # improvement -10 -> -5 (ratio 0.5) and *accept* a deterioration -10 -> -12 (ratio 1.2)
    s_min, s_max = -20.0, -4.0
    old = normalized_scores(torch.tensor([-10.0, -10.0]), s_min, s_max)
    new = normalized_scores(torch.tensor([-5.0, -12.0]), s_min, s_max)
    assert improves(new, old, 1.1).tolist() == [True, False]
    # the dataset minimum (ŝ = 0) accepts any strict increase
    assert improves(torch.tensor([0.01, 0.0]), torch.tensor([0.0, 0.0]), 1.1).tolist() == [True, False]
    with pytest.raises(ValueError, match="s_max > s_min"):
        normalized_scores(torch.zeros(2), 1.0, 1.0)


def test_adaptive_flow_steps_uses_worst_topk_block():
    scores = torch.arange(10.0)
    ids = torch.tensor([0, 0, 1, 1, 2, 2, 3, 3, 4, 4])  # K = 5
    top3 = scores.argsort(descending=True)[:3]  # 9, 8, 7 -> worst in block id 3 -> i = 4
    assert adaptive_flow_steps(ids, top3, scores) == 1
    top6 = scores.argsort(descending=True)[:6]  # worst = 4 -> block id 2 -> i = 3
    assert adaptive_flow_steps(ids, top6, scores) == 2


def test_validity_checks_each_condition():
    data = make_toy_dataset(num_trajectories=6, horizon=H, seed=0)
    from torchrl_ftb.diffusion import TrajectoryNormalizer

    x = torch.cat([data["observation"], data["action"]], -1)
    norm = TrajectoryNormalizer(5).fit(x, data["mask"])
    ok = trajectory_validity(data, normalizer=norm, min_length=1)
    assert ok["valid"].all()
    bad = data.select("observation", "action", "mask").clone()
    bad["observation"][0, 0, 0] = float("nan")
    bad["observation"][1, 0, 0] = 1e4  # far outside the data: |z| > 30
    bad["action"][2, 0, 1] = 2.0  # beyond the limit + tolerance (1 + 0.5)
    bad["mask"][3, 3:] = False
    out = trajectory_validity(bad, normalizer=norm, min_length=4)
    assert out["valid"].tolist() == [False, False, False, False, True, True]
    assert not out["finite"][0] and not out["in_bounds"][1] and not out["actions_ok"][2] and not out["long_enough"][3]


def test_flow_with_stand_in_sampler_improves_and_pools():
    data = make_toy_dataset(num_trajectories=40, horizon=H, seed=1)
    flow = FlowToBetter(_shift_sampler(0.2), _sum_ax, top_k=8, threshold=1.0, flow_steps=3, progress=False,
                        true_reward_fn=toy_reward, early_stop_fraction=0.0)
    res = flow(data)
    assert res.trajectories.batch_size == torch.Size([8, H])
    assert len(res.stats) == 3
    # every accepted sample scored above its condition; the final set beats the original top-k
    assert res.summary["score_mean_after"] > res.summary["score_mean_before"]
    assert res.summary["true_return_mean_after"] > res.summary["true_return_mean_before"]
    assert torch.allclose(res.scores.float(), _sum_ax(res.trajectories).double().float(), atol=1e-4)
    # cached true returns (only replaced trajectories hit the oracle) agree with a recomputation
    assert torch.allclose(res.true_returns, masked_true_return(res.trajectories, toy_reward), atol=1e-5)
    # final = top-k of original ∪ accepted (sorted), with provenance
    pool = torch.cat([res.original_scores, _sum_ax(res.generated).double()])
    assert torch.allclose(res.scores, pool.sort(descending=True).values[:8], atol=1e-4)
    assert (res.source_step > 0).any()
    # the stats' score curve is non-decreasing (current trajectories only change when improved)
    means = [r["score_mean"] for r in res.stats]
    assert all(b >= a - 1e-9 for a, b in zip(means, means[1:]))
    improved, stats = res  # tuple-style unpacking
    assert improved is res.trajectories and stats is res.stats
    # BC transitions: the valid (s, a) steps of the final set
    rb = FlowToBetter.to_replay_buffer(res, batch_size=16)
    assert len(rb) == int(res.trajectories["mask"].sum())
    assert set(rb.sample().keys()) == {"observation", "action"}


def test_samples_are_scored_as_they_are_kept_with_actions_clipped():
    """A sample whose actions overshoot the limit (within the tolerance) is kept with them clipped; it is scored,
    accepted and ranked by that clipped trajectory, not by the overshoot the score model would reward."""
    data = make_toy_dataset(num_trajectories=40, horizon=H, seed=1)

    def overshoot(cond):
        out = cond.select("observation", "action", "mask").clone()
        out["action"] = torch.where(out["mask"][..., None], out["action"] + 0.45, out["action"])  # up to 1.45
        return out

    flow = FlowToBetter(TensorDictModule(overshoot, ["condition"], ["sample"]), _sum_ax, top_k=8, threshold=1.0,
                        flow_steps=2, progress=False, early_stop_fraction=0.0)
    res = flow(data)
    assert res.generated.batch_size[0] > 0 and bool((res.trajectories["action"].abs() <= 1.0).all())
    torch.testing.assert_close(res.scores, _sum_ax(res.trajectories).double())


def test_keep_reward_flows_range_check_the_generated_reward():
    """With ``keep_reward`` (augmentation) the validity check's normaliser covers the reward channel: a sample that
    improves the score but carries a reward far outside the data's is invalid (it was never range-checked)."""
    data = make_toy_dataset(num_trajectories=30, horizon=H, seed=2)

    def with_reward(big: bool):
        def better(cond):
            out = cond.select("observation", "action", "mask", ("next", "reward")).clone()
            out["action"][..., 0] = (out["action"][..., 0] + 0.3).clamp(-1, 1) * out["mask"]
            if big:
                out["next", "reward"] = out["next", "reward"] + 1e3
            return out
        return TensorDictModule(better, ["condition"], ["sample"])

    accepted = {big: FlowToBetter(with_reward(big), _sum_ax, top_k=6, threshold=1.0, flow_steps=1, progress=False,
                                  keep_reward=True)(data).generated.batch_size[0] for big in (False, True)}
    assert accepted[False] > 0 and accepted[True] == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_flow_with_a_cuda_sampler_on_data_without_a_device():
    """The toy data's TensorDict has no device; a sampler on CUDA: the samples come back to the data's tensors'
    device (they stayed on CUDA and the flow mixed devices)."""
    data = make_toy_dataset(num_trajectories=20, horizon=H, seed=1)
    assert data.device is None
    sampler = _shift_sampler(0.2)

    class OnCuda(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.anchor = torch.nn.Parameter(torch.zeros(1, device="cuda"))

        def forward(self, td):
            return sampler(td.to("cuda"))

    res = FlowToBetter(OnCuda(), _sum_ax, top_k=4, threshold=1.0, flow_steps=1, progress=False)(data)
    assert res.trajectories["action"].device.type == "cpu" and res.generated.batch_size[0] > 0


def _lottery_sampler():
    """A stand-in sampler drawing, per sample and uniformly, one of: better but invalid (y-action 3),
    worse, or better (x-actions +0.2)."""

    def draw(cond):
        out = cond.select("observation", "action", "mask").clone()
        m = out["mask"][..., None]
        kind = torch.randint(0, 3, (cond.batch_size[0],))
        act = out["action"].clone()
        shift = torch.tensor([0.4, -0.3, 0.2])[kind]
        act[..., 0] = (act[..., 0] + shift[:, None]).clamp(-1, 1)
        act[kind == 0, :, 1] = 3.0
        out["action"] = act * m
        return out

    return TensorDictModule(draw, ["condition"], ["sample"])


def test_flow_candidates_propose_the_best_valid_sample():
    data = make_toy_dataset(num_trajectories=200, horizon=H, seed=3)
    res = {}
    for n in (1, 8):
        flow = FlowToBetter(_lottery_sampler(), _sum_ax, top_k=100, threshold=1.0, flow_steps=1, candidates=n,
                            progress=False, seed=4)
        res[n] = flow(data)
        # never an invalid proposal (the better-scoring invalid draws lose to valid ones)
        assert bool((res[n].generated["action"].abs() <= 1.0).all())
    # one draw: about a third of the conditions improve; best of 8: all but about (2/3)^8 of them
    assert 0.2 < res[1].stats[0]["accept_rate"] < 0.5
    assert res[8].stats[0]["accept_rate"] > 0.85
    assert 0.55 < res[8].stats[0]["candidate_valid_rate"] < 0.8 and "candidate_valid_rate" not in res[1].stats[0]
    assert res[8].summary["candidates"] == 8.0
    assert res[8].summary["score_mean_after"] > res[1].summary["score_mean_after"]
    with pytest.raises(ValueError, match="candidates must be >= 1"):
        FlowToBetter(_lottery_sampler(), _sum_ax, top_k=4, flow_steps=1, candidates=0)


def test_flow_rejects_invalid_samples_and_stops_early():
    data = make_toy_dataset(num_trajectories=30, horizon=H, seed=2)
    for corrupt in ("big_action", "short"):
        flow = FlowToBetter(_shift_sampler(0.3, corrupt=corrupt), _sum_ax, top_k=5, threshold=1.0, flow_steps=4,
                            min_length=8, progress=False)
        res = flow(data)
        assert res.generated.batch_size[0] == 0, corrupt
        assert len(res.stats) == 1  # nothing improved -> early stop after the first step
        assert torch.equal(res.scores, res.original_scores)
    with pytest.raises(ValueError, match="top_k"):
        FlowToBetter(_shift_sampler(), _sum_ax, top_k=31, flow_steps=1, progress=False)(data)
    nan_scores = _sum_ax(data).double()
    nan_scores[[3, 7]] = float("nan")
    with pytest.raises(ValueError, match=r"2 dataset scores are NaN or infinite \(trajectories \[3, 7\]\)"):
        FlowToBetter(_shift_sampler(), _sum_ax, top_k=5, flow_steps=1, progress=False)(data, scores=nan_scores)
    with pytest.raises(ValueError, match="num_blocks"):
        FlowToBetter(_shift_sampler(), _sum_ax, top_k=3)


def test_validity_fn_is_anded_with_the_generic_checks():
    data = make_toy_dataset(num_trajectories=30, horizon=H, seed=2)
    calls = []

    def only_even(samples):  # a domain check: keep the samples of even conditions
        calls.append(samples.batch_size[0])
        return torch.arange(samples.batch_size[0]) % 2 == 0

    flow = FlowToBetter(_shift_sampler(0.3), _sum_ax, top_k=6, threshold=1.0, flow_steps=1, progress=False,
                        validity_fn=only_even)
    res = flow(data)
    assert calls == [6]
    assert res.generated.batch_size[0] == 3  # improving samples, half of them domain-valid
    assert res.stats[0]["domain_valid_rate"] == pytest.approx(0.5)
    assert res.stats[0]["accept_rate"] == pytest.approx(0.5)
    bad = FlowToBetter(_shift_sampler(0.3), _sum_ax, top_k=6, flow_steps=1, progress=False,
                       validity_fn=lambda s: torch.ones(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="validity_fn returned shape"):
        bad(data)


def test_metaworld_frame_stack_check_rejects_inconsistent_frames():
    from tensordict import TensorDict

    from torchrl_ftb.envs import metaworld_frame_stack_check

    obs = torch.randn(3, 6, 39) * 0.1
    obs[:, 1:, 18:36] = obs[:, :-1, 0:18]  # real data: the stacked frame is the previous step
    obs[1, 3, 18:21] += 0.05  # one transition 5 cm off: mean error 1 cm over 5 transitions
    obs[2, 2:, 18:21] += 0.3
    mask = torch.ones(3, 6, dtype=torch.bool)
    mask[0, 4:] = False
    obs[0, 4:] = 9.0  # padding never counts
    td = TensorDict({"observation": obs, "mask": mask}, [3, 6])
    assert metaworld_frame_stack_check(0.02)(td).tolist() == [True, True, False]
    assert metaworld_frame_stack_check(0.005)(td).tolist() == [True, False, False]
    with pytest.raises(ValueError, match="max_error"):
        metaworld_frame_stack_check(-1.0)


class _TwoMembers(ScoreModel):
    """A 2-member "ensemble": member 0 scores x-actions (what the sampler pushes up), member 1
    y-actions (untouched by it): the members disagree about every sample."""

    def __init__(self):
        super().__init__(3, 2, num_cells=4, num_members=2)

    def score(self, trajs, *, members=False):
        m = trajs["mask"]
        per = torch.stack([(trajs["action"][..., 0] * m).sum(-1), (trajs["action"][..., 1] * m).sum(-1)])
        return per if members else per.mean(0)


def test_ensemble_rule_all_rejects_what_one_member_does_not_confirm():
    data = make_toy_dataset(num_trajectories=30, horizon=H, seed=4)
    kw = dict(top_k=6, threshold=1.0, flow_steps=2, progress=False, early_stop_fraction=0.0,
              true_reward_fn=toy_reward)
    mean_rule = FlowToBetter(_shift_sampler(0.3), _TwoMembers(), **kw)(data)
    assert mean_rule.generated.batch_size[0] > 0  # the mean score rises with member 0
    assert "accepted_true_gain_mean" in mean_rule.stats[0]
    all_rule = FlowToBetter(_shift_sampler(0.3), _TwoMembers(), ensemble_rule="all", **kw)(data)
    assert all_rule.generated.batch_size[0] == 0  # member 1 never sees an improvement
    assert torch.equal(all_rule.scores, all_rule.original_scores)
    with pytest.raises(ValueError, match="ensemble"):
        FlowToBetter(_shift_sampler(), _sum_ax, ensemble_rule="all", **kw)
    with pytest.raises(ValueError, match="ensemble_rule"):
        FlowToBetter(_shift_sampler(), _sum_ax, ensemble_rule="min", **kw)


def test_adaptive_zero_steps_warns_and_uses_floor():
    data = make_toy_dataset(num_trajectories=30, horizon=H, seed=3)
    scores = _sum_ax(data).double()
    ids = (scores >= scores.sort().values[-5]).long()  # 2 blocks; the top 5 all in the last block
    flow = FlowToBetter(_shift_sampler(), _sum_ax, top_k=5, threshold=1.0, num_blocks=2, progress=False)
    with pytest.warns(UserWarning, match="adaptive flow steps"):
        res = flow(data, scores=scores, block_ids=ids)
    assert res.summary["flow_steps_adaptive"] == 0 and res.summary["flow_steps_planned"] == 1


def test_true_return_stop_rule_fill_pays_a_faster_success_more():
    # two trajectories of per-step reward 1 (the action): one done in 2 steps, one running all 4
    td = TensorDict({"observation": torch.zeros(2, 4, 1), "action": torch.ones(2, 4, 1),
                     "mask": torch.tensor([[True, True, False, False], [True] * 4])}, [2, 4])
    reward = lambda o, a: a.sum(-1)  # noqa: E731
    both = masked_true_returns(td, reward, horizons=(None, 6))
    assert both.tolist() == [[2.0, 6.0], [4.0, 6.0]]  # plain: the longer earns more; filled: both run 6 steps
    td["action"][0, 1] = 3.0  # the short one ends on a high reward, which it keeps earning
    assert masked_true_return(td, reward, horizon=6).tolist() == [1.0 + 3.0 * 5, 6.0]
    assert improvement(td[:1], td[1:], true_reward_fn=reward, horizon=6)["true_return_mean_before"] == 16.0
    with pytest.raises(ValueError, match="horizon"):
        masked_true_returns(td, reward, horizons=(0,))


def test_stop_rule_cut_scores_a_sample_as_if_its_episode_had_stopped():
    # per-step reward = the action, success = reward >= 5; a stop rule of 2 consecutive successes
    td = TensorDict({"observation": torch.zeros(3, 6, 1), "action": torch.tensor([[1., 5., 6., 7., 8., 9.],
                                                                                   [1., 5., 1., 5., 6., 2.],
                                                                                   [1., 5., 1., 5., 1., 0.]])[..., None],
                     "mask": torch.tensor([[True] * 6, [True] * 5 + [False], [True] * 5 + [False]])}, [3, 6])

    def reward_and_success(o, a):
        r = a.sum(-1)
        return r, r >= 5

    cols = masked_true_returns(td, reward_and_success, horizons=(None, 6, 6), streaks=(None, None, 2))
    # row 0: the rule stops it after step 2 (5, 6 succeed): 1 + 5 + 6, then 6 kept for the 3 remaining steps
    assert cols[0].tolist() == [36.0, 36.0, 12.0 + 3 * 6.0]
    # row 1: its streak (5, 6) ends at its 5th step: the cut keeps all 5 steps; fill 1 step of 6
    assert cols[1].tolist() == [18.0, 24.0, 24.0]
    # row 2: it ends early with no streak (a generated length, not a stop): the plain fill pays its last
    # reward for the missing step as if it had succeeded; the stop-rule column does not
    assert cols[2].tolist() == [13.0, 14.0, 13.0]
    # a plain reward function still works without streaks, and is refused with them
    reward = lambda o, a: a.sum(-1)  # noqa: E731
    assert masked_true_returns(td, reward, horizons=(None,))[:, 0].tolist() == [36.0, 18.0, 13.0]
    with pytest.raises(ValueError, match=r"streaks= needs a true_reward_fn that returns \(reward, success\)"):
        masked_true_returns(td, reward, horizons=(6,), streaks=(2,))
    with pytest.raises(ValueError, match="one entry"):
        masked_true_returns(td, reward_and_success, horizons=(6,), streaks=(2, 2))
    # in the flow: a third column, stop_rule, beside plain and filled
    data = make_toy_dataset(num_trajectories=40, horizon=H, seed=1)

    def toy_with_success(o, a):
        r = toy_reward(o, a)
        return r, r.reshape(-1) > 0

    flow = FlowToBetter(_shift_sampler(0.2), _sum_ax, top_k=8, threshold=1.0, flow_steps=1, progress=False,
                        true_reward_fn=toy_with_success, true_return_horizon=2 * H, true_return_streak=3,
                        early_stop_fraction=0.0)
    res = flow(data)
    expected = masked_true_returns(res.trajectories, toy_with_success, horizons=(2 * H,), streaks=(3,))[:, 0]
    assert res.summary["true_return_filled_stop_rule_mean_after"] == pytest.approx(float(expected.mean()))
    assert res.summary["true_return_streak"] == 3 and "true_return_filled_stop_rule_max" in res.stats[0]
    assert torch.allclose(res.filled_true_returns, masked_true_return(res.trajectories, toy_reward, horizon=2 * H),
                          atol=1e-5)
    with pytest.raises(ValueError, match="true_return_streak needs a true_return_horizon"):
        FlowToBetter(_shift_sampler(0.2), _sum_ax, top_k=8, flow_steps=1, true_reward_fn=toy_with_success,
                     true_return_streak=3)
    # each column's gain of the accepted samples over what they replaced: one step, so each sample's own
    # condition, the original with the same observations (the stand-in sampler moves only actions)
    gen, orig = res.generated, res.original
    assert gen.batch_size[0] > 0
    slot = [int((orig["observation"] == g).flatten(1).all(1).nonzero()[0]) for g in gen["observation"]]
    cols = dict(horizons=(None, 2 * H, 2 * H), streaks=(None, None, 3))
    true_of = functools.partial(masked_true_returns, true_reward_fn=toy_with_success, **cols)
    gain = true_of(gen) - true_of(orig[slot])
    for j, key in enumerate(["accepted_true_gain", "accepted_true_return_filled_gain",
                             "accepted_true_return_filled_stop_rule_gain"]):
        assert res.stats[0][f"{key}_mean"] == pytest.approx(float(gain[:, j].mean()))
        assert res.stats[0][f"{key}_positive"] == pytest.approx(float((gain[:, j] > 0).double().mean()))


def test_flow_reports_the_filled_true_return_beside_the_plain_one():
    data = make_toy_dataset(num_trajectories=40, horizon=H, seed=1)
    flow = FlowToBetter(_shift_sampler(0.2), _sum_ax, top_k=8, threshold=1.0, flow_steps=2, progress=False,
                        true_reward_fn=toy_reward, true_return_horizon=2 * H, early_stop_fraction=0.0)
    res = flow(data)
    filled = masked_true_return(res.trajectories, toy_reward, horizon=2 * H)
    assert torch.allclose(res.filled_true_returns, filled, atol=1e-5)
    assert torch.allclose(res.true_returns, masked_true_return(res.trajectories, toy_reward), atol=1e-5)
    assert res.summary["true_return_filled_mean_after"] == pytest.approx(float(filled.mean()))
    assert res.summary["true_return_horizon"] == 2 * H
    assert {"true_return_filled_mean", "true_return_filled_max", "true_return_mean"} <= set(res.stats[0])
    with pytest.raises(ValueError, match="true_return_horizon"):
        FlowToBetter(_shift_sampler(0.2), _sum_ax, top_k=8, flow_steps=1, true_return_horizon=10)


def test_oracle_filter_starts_from_the_true_top_k_and_keeps_only_true_gains():
    data = make_toy_dataset(num_trajectories=40, horizon=H, seed=1)
    oracle = true_return_score(toy_reward)

    def push_x_and_swerve(cond):  # raises sum(a_x) always; swerving (a_y = 0.9) costs more on half of them
        out = cond.select("observation", "action", "mask").clone()
        act = out["action"].clone()
        act[..., 0] = (act[..., 0] + 0.3).clamp(-1, 1)
        act[1::2, :, 1] = 0.9
        out["action"] = act * out["mask"][..., None]
        return out

    sampler = TensorDictModule(push_x_and_swerve, ["condition"], ["sample"])
    kw = dict(top_k=8, threshold=1.0, flow_steps=2, progress=False, true_reward_fn=toy_reward, early_stop_fraction=0.0)
    res = FlowToBetter(sampler, oracle, **kw)(data)
    true_all = masked_true_return(data, toy_reward)
    assert set(res.original_indices.tolist()) == set(true_all.argsort(descending=True)[:8].tolist())
    assert torch.allclose(res.scores, res.true_returns, atol=1e-6)  # the filter's score is the true return
    gained = [row["accepted_true_gain_positive"] for row in res.stats if "accepted_true_gain_positive" in row]
    assert gained and all(g == 1.0 for g in gained)
    assert res.summary["true_return_mean_after"] >= res.summary["true_return_mean_before"]
    # an imperfect filter (sum of a_x, blind to the swerve) lets true losses in; its top-k is no better
    stand_in = FlowToBetter(sampler, _sum_ax, **kw)(data)
    assert min(row["accepted_true_gain_positive"] for row in stand_in.stats) < 1.0
    assert res.summary["true_return_mean_before"] >= stand_in.summary["true_return_mean_before"] - 1e-6


def test_analysis_metrics_and_plots(tmp_path):
    data = make_toy_dataset(num_trajectories=12, horizon=H, seed=0)
    ret = masked_true_return(data, toy_reward)
    assert torch.allclose(ret.float(), true_return(data), atol=1e-4)
    out = improvement(data[:4], data[4:8], true_reward_fn=toy_reward)
    assert out["true_return_mean_after"] == pytest.approx(float(ret[4:8].mean()))
    oracle = lambda o, a: toy_oracle_step(o, a, horizon=H)  # noqa: E731
    assert dynamics_error(data, oracle)["mean"] < 1e-5  # real transitions obey the dynamics
    fake = data.select("observation", "action", "mask").clone()
    fake["action"] = fake["action"] * 0 + 0.5  # actions no longer explain the observations
    assert dynamics_error(fake, oracle)["mean"] > 1e-3
    # novelty: a copy of the dataset has distance 0; perturbed copies are ~noise away
    nov = novelty(data[:5].select("observation", "action", "mask"), data, noise_std=0.1, seed=0)
    assert nov["generated_mean"] == pytest.approx(0.0, abs=1e-5) and nov["perturbed_mean"] > 0.1
    p1 = plot_flow_curves([{"step": 1, "score_mean": 1.0, "score_max": 2.0, "true_return_mean": 3.0,
                            "true_return_max": 4.0, "accept_rate": 0.5}], tmp_path / "f.png",
                          before={"score_mean": 0.5, "score_max": 1.0})
    p2 = plot_histograms({"a": ret, "b": ret + 1}, tmp_path / "h.png", xlabel="return")
    assert p1.stat().st_size > 1000 and p2.stat().st_size > 1000


@functools.lru_cache(maxsize=1)
def _trained_toy_parts():
    """A small trained score model and trajectory diffuser on toy data with room above its best
    (qualities up to 0.7 only): ``(data, score_model, scores, blocks, diffuser)``, built once."""
    from torchrl_ftb.diffusion import make_diffuser, train_diffuser
    from torchrl_ftb.preference import make_block_pair_buffer, make_blocks, score_trajectories, train_score_model

    n = 96
    data = make_toy_dataset(num_trajectories=n, horizon=H, seed=0, quality=torch.linspace(-0.5, 0.7, n))
    labels = make_scripted_labels(data, num_pairs=100, teacher=make_teacher("return"), seed=0)
    score_model = ScoreModel(3, 2, num_cells=32, seed=0)
    train_score_model(score_model, labels, steps=200, lr=3e-3, eval_fraction=0.0, seed=0, progress=False)
    scores = score_trajectories(score_model, data)
    blocks = make_blocks(scores, 4, seed=0)
    diffuser = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H).fit_normalizer(data)
    buffer = make_block_pair_buffer(data, blocks, batch_size=32, seed=0)
    train_diffuser(diffuser, buffer, steps=250, lr=3e-3, grad_clip=1.0, seed=0, progress=False)
    return data, score_model, scores, blocks, diffuser


def test_flow_with_trained_diffuser_and_score_model_improves_toy_trajectories():
    """Real modules: a small trained score model + trajectory diffuser on the toy task."""
    from torchrl_ftb.diffusion import DiffusionSampler

    data, score_model, scores, blocks, diffuser = _trained_toy_parts()
    sampler = DiffusionSampler(diffuser, sampler="ddpm", steps=50, guidance=1.2,
                               generator=torch.Generator().manual_seed(0))
    flow = FlowToBetter(sampler, score_model, top_k=40, threshold=1.05, flow_steps=2, early_stop_fraction=0.0,
                        true_reward_fn=toy_reward, seed=0, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = flow(data, scores=scores, block_ids=blocks)
    first = res.stats[0]
    # conditioned on the top-k (many already in the top block, which no training pair maps
    # from), a good share of the samples is valid and beats its own condition by sigma
    assert first["valid_rate"] > 0.9 and first["accept_rate"] >= 0.2
    assert res.generated.batch_size[0] > 0
    # every accepted sample beats its condition, so the set's score and true return go up
    assert res.summary["score_mean_after"] > res.summary["score_mean_before"]
    assert res.summary["true_return_mean_after"] > res.summary["true_return_mean_before"]
    gen_true = masked_true_return(res.generated, toy_reward)
    assert float(gen_true.mean()) > float(masked_true_return(res.original, toy_reward).mean())


def test_score_guidance_lifts_the_top_blocks_samples_above_the_data():
    """diffuser.score_guidance: climbing s_psi's gradient while sampling moves the top block's samples up in
    *true* return, past the dataset's best, and the flow then raises the set's true max; scale 0 is no guide."""
    from torchrl_ftb.diffusion import DiffusionSampler
    from torchrl_ftb.preference import score_objective

    data, score_model, scores, blocks, diffuser = _trained_toy_parts()
    objective = score_objective(score_model, float(scores.min()), float(scores.max()))
    top = data[blocks == blocks.max()]

    def samples(scale: float, guide=objective):
        return diffuser.generate(top, sampler="ddpm", steps=50, generator=torch.Generator().manual_seed(0),
                                 guide=guide, guide_scale=scale)

    score_model.zero_grad(set_to_none=True)  # (training left its last gradients)
    plain, guided = samples(0.0, guide=None), samples(0.3)
    # the guide reads gradients w.r.t. the sample only; an objective that ignores the sample moves nothing
    assert all(p.grad is None for p in score_model.parameters())
    constant = samples(0.3, guide=lambda trajs: torch.zeros(trajs.batch_size[0]))
    assert torch.equal(constant["observation"], plain["observation"])
    before, after = masked_true_return(plain, toy_reward), masked_true_return(guided, toy_reward)
    best = float(masked_true_return(data, toy_reward).max())
    above = lambda r: int((r > best).sum())  # noqa: E731
    print(f"top block: true return mean {before.mean():.2f} -> {after.mean():.2f}, above the data's best "
          f"({best:.2f}) {above(before)} -> {above(after)} of {top.batch_size[0]}")
    assert float(after.mean()) > float(before.mean()) + 2.0
    assert above(after) > above(before) + 3
    with torch.no_grad():
        assert float(objective(guided).mean()) > float(objective(plain).mean())

    def flowed(scale: float) -> dict:
        sampler = DiffusionSampler(diffuser, sampler="ddpm", steps=50, generator=torch.Generator().manual_seed(0),
                                   guide=objective if scale else None, guide_scale=scale)
        flow = FlowToBetter(sampler, score_model, top_k=20, threshold=1.05, flow_steps=2, early_stop_fraction=0.0,
                            true_reward_fn=toy_reward, seed=0, progress=False)
        return flow(data, scores=scores, block_ids=blocks).summary

    plain_flow, guided_flow = flowed(0.0), flowed(0.3)
    print({k: (round(plain_flow[k], 2), round(guided_flow[k], 2)) for k in
           ("true_return_mean_before", "true_return_mean_after", "true_return_max_after")})
    assert guided_flow["true_return_mean_after"] > plain_flow["true_return_mean_after"] + 0.5
    # bad input: a scale without an objective, a negative scale
    with pytest.raises(ValueError, match="needs a guide objective"):
        DiffusionSampler(diffuser, guide_scale=0.3)
    with pytest.raises(ValueError, match="guide_scale must be a finite number >= 0"):
        DiffusionSampler(diffuser, guide=objective, guide_scale=-1.0)
    with pytest.raises(ValueError, match="one number per trajectory"):
        diffuser.generate(top[:2], sampler="ddim", steps=2, guide=lambda t: t["action"].sum(), guide_scale=0.1)


def test_flow_hands_the_sampler_each_conditions_normalised_score():
    """Every flow step's conditions carry ŝ of the *current* trajectory on the dataset's scale
    (what a ``score_condition`` diffuser reads), updated after each accepted sample."""
    data = make_toy_dataset(num_trajectories=40, horizon=H, seed=0)
    inner, seen = _shift_sampler(0.3), []

    def record(cond):
        seen.append((cond[NORMALIZED_SCORE_KEY][:, 0].clone(), _sum_ax(cond)))
        return inner.module(cond)

    flow = FlowToBetter(TensorDictModule(record, ["condition"], ["sample"]), _sum_ax, top_k=6, threshold=1.0,
                        flow_steps=2, early_stop_fraction=0.0, progress=False)
    scores = _sum_ax(data).double()
    flow(data)
    assert len(seen) == 2
    for hat, raw in seen:
        expected = normalized_scores(raw.double(), float(scores.min()), float(scores.max()))
        assert torch.allclose(hat.double(), expected, atol=1e-5)
    assert bool((seen[1][0] > seen[0][0]).any())  # accepted samples moved their conditions' ŝ up
