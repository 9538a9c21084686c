"""bench/diffuser_conditioning.py (top-block conditions) and bench/open_loop.py (replay returns) on small inputs."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from torchrl_ftb.data.labels import true_return
from torchrl_ftb.diffusion import make_diffuser
from torchrl_ftb.preference import ScoreModel
from torchrl_ftb.testing import load_script, make_toy_dataset, toy_reward

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.filterwarnings("ignore::UserWarning"), pytest.mark.usefixtures("one_thread")]


def _toy_run(stride: int = 1):
    """A toy dataset of 40 trajectories (H = 16) in four ascending blocks of ten by true return, a tiny diffuser
    of its every ``stride``-th step and an untrained score model: what ``evaluate`` reads of a run."""
    data = make_toy_dataset(num_trajectories=40, horizon=16, seed=0)
    trajs = data.select("observation", "action", "mask")
    returns = true_return(data).double()
    ids = torch.empty(40, dtype=torch.long)
    ids[returns.argsort()] = torch.arange(40) // 10
    obs_dim, act_dim = trajs["observation"].shape[-1], trajs["action"].shape[-1]
    diffuser = make_diffuser("tiny", obs_dim=obs_dim, action_dim=act_dim, horizon=16 // stride,
                             data=trajs[:, ::stride], hidden_dim=16, cond_dim=16)
    return trajs, returns, ids, diffuser, ScoreModel(obs_dim, act_dim, num_cells=16, seed=0)


def test_top_block_conditions_have_no_target_and_keep_the_other_blocks_statistics(tmp_path):
    bench = load_script(ROOT / "bench" / "diffuser_conditioning.py", "bench_diffuser_conditioning")
    trajs, returns, ids, diffuser, model = _toy_run()
    kw = dict(per_block=3, sampler="ddim", steps=2, guidance=1.2, seed=0, returns=returns, reward_fn=toy_reward)
    base = bench.evaluate(diffuser, model, trajs, returns, ids, **kw)
    top = bench.evaluate(diffuser, model, trajs, returns, ids, top_block=True, **kw)

    assert list(base["per_condition_block"]) == ["1", "2", "3"] and base["num_conditions"] == 9
    assert list(top["per_condition_block"]) == ["1", "2", "3", "4"] and top["num_conditions"] == 12
    b4 = top["per_condition_block"]["4"]
    assert b4["target_block_score"] is None and b4["target_block_true_return"] is None
    assert b4["condition_true_return_max"] <= float(returns.max()) + 1e-9
    assert b4["condition_true_return"] >= float(returns[ids == 3].min()) - 1e-9  # conditions from the top block
    assert 0.0 <= b4["samples_above_condition"] <= 1.0
    assert set(top["start_gap"]) == {"z_own", "z_other"}  # no Meta-World parts on the toy
    # a sample that starts where its condition does: own gap 0, below the other conditions'
    starts = torch.zeros(6, 39)
    starts[:, 4:7] = torch.rand(6, 3, generator=torch.Generator().manual_seed(0)) * 0.1
    gaps = bench.start_gaps_to_conditions(starts, starts, starts)
    assert gaps["z_own"] == 0.0 and gaps["object_cm_own"] == 0.0 and gaps["object_cm_other"] > 1.0
    assert gaps["goal_cm_other"] == 0.0  # one goal
    # the trajectory gap: a copy is 0 from its own condition and about 2 from the others (unit-variance dims)
    copy = bench.trajectory_gaps_to_conditions(diffuser, trajs[:8], trajs[:8])
    assert copy["own"] == 0.0 and 1.0 < copy["other"] < 4.0, copy
    assert top["trajectory_gap"]["own"] > 0.0 and top["trajectory_gap"]["other"] > 0.0
    for k in ("1", "2", "3"):  # the same conditions and targets for the blocks the pairs use
        for field in ("condition_score", "target_block_score", "condition_true_return", "target_block_true_return"):
            assert top["per_condition_block"][k][field] == pytest.approx(base["per_condition_block"][k][field])

    path = tmp_path / "toy-top.json"
    path.write_text(json.dumps({"evaluations": [{**top, "step": 0}]}))
    table = bench.summarize([path]).splitlines()
    assert "B4 (top: no target) → sample" in table[0]
    b4 = top["per_condition_block"]["4"]
    assert table[2].endswith(f"(—); above own condition {b4['samples_above_condition']:.0%}, max "
                             f"{b4['sample_true_return_max']:.0f} (conditions' {b4['condition_true_return_max']:.0f}) |")
    assert len(table) == 3


def test_a_coarse_diffuser_is_conditioned_on_coarse_trajectories_and_read_at_the_datas_horizon(tmp_path):
    """--stride: the diffuser sees every stride-th step; samples are refined back to the data's horizon before the
    score model and the true reward read them, and the conditions' own round trip is reported beside them."""
    bench = load_script(ROOT / "bench" / "diffuser_conditioning.py", "bench_diffuser_conditioning_stride")
    trajs, returns, ids, diffuser, model = _toy_run(stride=2)
    seen = []
    generate = diffuser.generate

    def spy(cond, **kw):
        seen.append(cond.batch_size)
        out = generate(cond, **kw)
        seen.append(out.batch_size)
        return out

    lengths_read = []

    def reward(observation, action):
        lengths_read.append(observation.shape[-2])
        return toy_reward(observation, action)

    diffuser.generate = spy
    out = bench.evaluate(diffuser, model, trajs, returns, ids, per_block=3, sampler="ddim", steps=2, guidance=1.2,
                         seed=0, returns=returns, reward_fn=reward, stride=2)
    assert seen == [torch.Size([9, 8]), torch.Size([9, 8])]  # coarse conditions in, coarse samples out
    assert len(lengths_read) == 18  # 9 samples and 9 round trips, read at the data's horizon: even lengths > 8
    assert max(lengths_read) > 8 and all(n % 2 == 0 for n in lengths_read)
    for entry in out["per_condition_block"].values():
        assert {"condition_round_trip_score", "condition_round_trip_true_return",
                "samples_above_round_trip"} <= set(entry)
    path = tmp_path / "toy-stride.json"
    path.write_text(json.dumps({"evaluations": [{**out, "step": 0}]}))
    row = bench.summarize([path]).splitlines()[2]
    assert row.count("conditions' round trip") == 3


def test_open_loop_replay_returns_fill_only_where_the_stop_rule_ended_the_replay():
    """torchrl_ftb.analysis.replay_returns (bench/open_loop.py, the recipe's analysis.open_loop): a replay
    ended by the success streak earns its last reward to the horizon; one that ran out of actions (or hit
    the limit) earns its own steps only."""
    import numpy as np

    from torchrl_ftb.datasets.metaworld import SUCCESS_STREAK

    from torchrl_ftb.analysis import nearest_start, replay_returns
    n = SUCCESS_STREAK + 5
    streak = {"reward": np.full(n, 2.0), "success": np.r_[np.zeros(5, bool), np.ones(SUCCESS_STREAK, bool)]}
    ran_out = {"reward": np.full(n, 2.0), "success": np.r_[np.zeros(6, bool), np.ones(SUCCESS_STREAK - 1, bool)]}
    out = replay_returns([streak, ran_out], horizon=100)
    assert out[:, 0].tolist() == [2.0 * n, 2.0 * n]
    assert out[:, 1].tolist() == [2.0 * n + 2.0 * (100 - n), 2.0 * n]
    rows, dist = nearest_start(torch.tensor([[0.0, 1.0], [5.0, 5.1]]),
                                     torch.tensor([[5.0, 5.0], [0.0, 1.0], [9.0, 9.0]]))
    assert rows.tolist() == [1, 0] and dist.tolist() == pytest.approx([0.0, 0.1])


def test_open_loop_summary_reads_bench_files_and_recipe_cells(tmp_path):
    """bench/open_loop.py --summarize: one row per run of its own files (old ones derive the sample columns
    from their samples) and per table1 cell whose run had analysis.open_loop."""
    bench = load_script(ROOT / "bench" / "open_loop.py", "bench_open_loop_summary")
    summ = {"true_return_mean_before": 10.0, "true_return_max_before": 20.0,
            "true_return_mean_after": 12.0, "true_return_max_after": 20.0}
    improvement = {"stop_rule_500": {"claimed": summ, "replayed": {**summ, "true_return_mean_after": 9.0}}}
    samples = [{"start_distance": d, "replay_success": s, "claimed_stop_rule": 30.0, "replayed_stop_rule": r}
                for d, s, r in ((0.005, True, 40.0), (0.05, False, 10.0))]
    old = tmp_path / "open_loop_old.json"
    old.write_text(json.dumps({"runs": {"/r/x/seed4": {"env": "drawer-open-v3", "seed": 4, "num_generated": 2,
                                                          "improvement": improvement, "samples": samples}}}))
    ol = {"num_generated": 0, "horizon": 500, "improvement": improvement}
    cell = tmp_path / "cells" / "ftb__drawer-open-v3__success__seed4.json"
    cell.parent.mkdir()
    cell.write_text(json.dumps({"metrics": {"env": "drawer-open-v3", "seed": 4, "eval": {"success_rate": 0.5},
                                            "analysis": {"open_loop": ol}}}))
    # a locomotion cell: plain returns, every trajectory replayed from its own start, the policy's D4RL score
    loco = tmp_path / "loco" / "ftb__hopper-medium-replay__return__seed0.json"
    loco.parent.mkdir()
    loco.write_text(json.dumps({"metrics": {"env": "hopper", "seed": 0, "eval": {"normalized_score": 7.5},
                                            "analysis": {"open_loop": {
                                                "num_generated": 3, "horizon": None, "claimed_plain_mean_generated": 300.0,
                                                "replayed_plain_mean_generated": 120.0,
                                                "improvement": {"plain": improvement["stop_rule_500"]}}}}}))
    rows = bench.summarize([old, cell, loco]).splitlines()
    assert len(rows) == 5 and rows[1].count("|") == rows[0].count("|") == rows[4].count("|")
    assert rows[2] == ("| open_loop_old | drawer-open-v3 s4 | 2 | 50% (0.5 cm) | — | 30 → 25 | 50% | "
                       "10 → 12 / **10 → 9** | 20 → 20 / **20 → 20** | — |")
    assert rows[3].startswith("| cells | drawer-open-v3 s4 | 0 | — |") and rows[3].endswith("| 0.50 |")
    assert rows[4] == ("| loco | hopper s0 | 3 | own start | — | 300 → 120 | — | "
                       "10 → 12 / **10 → 9** | 20 → 20 / **20 → 20** | 7.50 |")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"metrics": {"env": "x", "analysis": {}}}))
    with pytest.raises(SystemExit, match="analysis.open_loop"):
        bench.summarize([bad])


def test_tracked_replay_summary_reads_its_results_files(tmp_path):
    """bench/tracked_replay.py --summarize: one Markdown row per run, claimed beside tracked, and the max
    without the generated paths the tracker left (off path) where the file records it."""
    bench = load_script(ROOT / "bench" / "tracked_replay.py", "bench_tracked_summary")
    summ = lambda a, b, c, d: {"true_return_mean_before": a, "true_return_mean_after": b,  # noqa: E731
                               "true_return_max_before": c, "true_return_max_after": d}
    entry = {"env": "drawer-open-v3", "seed": 4, "inpaint_start": True, "tracked": summ(10, 12, 40, 41),
             "claimed": summ(11, 13, 42, 42),
             "fidelity": {"recorded_mean": 11.0, "tracked_mean": 10.0, "hand_deviation_median": 0.014},
             "generated": {"num_generated": 2, "claimed_stop_rule_mean": 5.0, "tracked_stop_rule_mean": 6.0,
                           "hand_deviation_median": 0.02, "tracked_success_rate": 0.5}}
    path = tmp_path / "t.json"
    path.write_text(json.dumps({"runs": {"/r/cell_x/drawer-open-v3/seed4": entry}}))
    rows = bench.summarize([path]).splitlines()
    assert rows[2] == ("| cell_x | drawer-open-v3 s4 | tracker | held | 2 | 11 → 10 (1.4 cm) | 5 → 6 (2.0 cm; 50%) | "
                       "11 → 13 / **10 → 12** | 42 → 42 / **40 → 41** | — |")  # a file from before session 32
    entry["generated"]["off_path"], entry["tracked_on_path"] = 1, summ(10, 11, 40, 40)
    path.write_text(json.dumps({"runs": {"/r/cell_x/drawer-open-v3/seed4": entry}}))
    assert bench.summarize([path]).splitlines()[2].endswith("/ **40 → 41** | 1 (of 2): 40 → 40 |")
    entry["shooting"] = {"candidates": 4, "readers": 4, "lookahead": 1}  # the default reading since session 52
    path.write_text(json.dumps({"runs": {"/r/cell_x/drawer-open-v3/seed4": entry}}))
    assert "| drawer-open-v3 s4 | shot 4×4 | held |" in bench.summarize([path])


def test_measure_runs_writes_after_every_run_with_its_provenance(tmp_path, capsys):
    """bench/flow_generated.py's measure_runs (open_loop, tracked_replay, hand_paths): each run's entry is in the
    results file as soon as it is measured, beside the command, config, commit and machine, so a job stopped
    after its first run keeps that run."""
    bench = load_script(ROOT / "bench" / "flow_generated.py", "bench_flow_generated_measure")
    out = tmp_path / "r.json"

    def measure(run):
        if run.name == "b":
            raise KeyboardInterrupt  # the job is stopped during its second run
        return {"value": 1.5}

    with pytest.raises(KeyboardInterrupt):
        bench.measure_runs([tmp_path / "a", tmp_path / "b"], out, {"horizon": 500}, measure,
                           lambda run, e: f"{run.name}: {e['value']}")
    record = json.loads(out.read_text())
    assert record["runs"] == {str(tmp_path / "a"): {"value": 1.5}}
    assert record["config"] == {"run_dirs": [str(tmp_path / "a"), str(tmp_path / "b")], "horizon": 500}
    assert {"command", "git_commit", "machine"} <= set(record)
    assert "a: 1.5" in capsys.readouterr().out


def test_pair_starts_measures_closer_starts_for_start_matched_pairs():
    bench = load_script(ROOT / "bench" / "pair_starts.py", "bench_pair_starts")
    g = torch.Generator().manual_seed(0)
    starts = torch.zeros(60, 39)  # one hand start, as on Meta-World; only the object and the goal vary
    starts[:, 4:7] = torch.rand(60, 3, generator=g) * 0.1
    starts[:, 36:39] = torch.rand(60, 3, generator=g) * 0.1
    ids = torch.arange(60) % 3
    kw = dict(pairs=4000, seed=0, metaworld=True)
    uniform = bench.start_gaps(starts, ids, neighbours=None, **kw)
    nearest = bench.start_gaps(starts, ids, neighbours=1, **kw)
    assert set(uniform) == {"z", "hand_cm", "object_cm", "goal_cm"} and uniform["hand_cm"] == 0.0
    assert nearest["z"] < 0.8 * uniform["z"] and nearest["object_cm"] < uniform["object_cm"]
    # m as large as a block: the same pairs as uniform ones, in distribution
    everyone = bench.start_gaps(starts, ids, neighbours=20, **kw)
    assert everyone["z"] == pytest.approx(uniform["z"], rel=0.05)


def test_coarsen_round_trip_reads_returns_per_block():
    bench = load_script(ROOT / "bench" / "coarsen_round_trip.py", "bench_coarsen_round_trip")
    before = torch.tensor([1.0, 3.0, 10.0, 30.0], dtype=torch.float64)
    after = torch.tensor([1.0, 1.0, 10.0, 20.0], dtype=torch.float64)
    out = bench.per_block(before, after, torch.tensor([0, 0, 1, 1]))
    assert list(out) == ["1", "2", "all"]
    assert out["1"]["before"] == 2.0 and out["1"]["after"] == 1.0 and out["1"]["kept"] == 0.5
    assert out["2"]["max_before"] == 30.0 and out["2"]["max_after"] == 20.0 and out["2"]["n"] == 2
    assert out["all"]["kept"] == pytest.approx(32.0 / 44.0)


@pytest.mark.parametrize("prediction_type,factor", [("epsilon", lambda a: (1 - a) / a), ("v_prediction", lambda a: 1 - a)])
def test_condition_use_reads_each_condition_and_the_x0_error_it_implies(prediction_type, factor):
    """bench/condition_use.py: per t, the error with the own, a rolled and the null condition; the implied x0
    error is the eps error times (1 - abar) / abar, the v error times (1 - abar)."""
    bench = load_script(ROOT / "bench" / "condition_use.py", "bench_condition_use")
    data = make_toy_dataset(num_trajectories=12, horizon=8, seed=0)
    diffuser = make_diffuser("tiny", obs_dim=data["observation"].shape[-1], action_dim=data["action"].shape[-1],
                             horizon=8, data=data, prediction_type=prediction_type, hidden_dim=16, cond_dim=16)
    diffuser.update_ema()
    out = bench.condition_use(diffuser, data, timesteps=(10, 900))
    assert list(out) == ["10", "900"]
    for row in out.values():
        for name in ("own", "shuffled", "null"):
            assert row[f"{name}_x0"] == pytest.approx(row[name] * factor(row["abar"]), rel=1e-3)
        assert row["own"] != row["shuffled"]  # the condition reaches the output


def test_plot_conditioning_draws_saved_results_and_names_a_file_without_true_returns(tmp_path):
    bench = load_script(ROOT / "bench" / "diffuser_conditioning.py", "bench_diffuser_conditioning")

    def block(sample, condition, target):
        return {"sample_score": 0.0, "target_block_score": None if target is None else 1.0,
                "sample_true_return": sample, "condition_true_return": condition, "target_block_true_return": target}

    evs = [{"step": s, "per_condition_block": {"1": block(10.0 + s, 5.0, 20.0), "2": block(15.0, 20.0, None)}}
           for s in (1500, 3000)]
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"evaluations": evs}))
    out = bench.plot_conditioning([good], tmp_path / "plots" / "c.png")
    assert out == tmp_path / "plots" / "c.png" and out.stat().st_size > 1000
    assert not list((tmp_path / "plots").glob(".*"))  # atomic write: no temp file left
    bare = tmp_path / "bare.json"  # a run without a reward oracle has no true returns
    bare.write_text(json.dumps({"evaluations": [{"step": 1500, "per_condition_block": {"1": {"sample_score": 0.0}}}]}))
    with pytest.raises(ValueError, match="bare.json: no evaluation with true returns"):
        bench.plot_conditioning([good, bare], tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_edits_of_the_condition_stay_near_it_and_inpainting_holds_its_start():
    """--strength < 1 samples SDEdit edits of each condition, --inpaint-start holds each sample's first
    observation at its condition's: the flow's diffuser.strength / diffuser.inpaint_start, read by the bench."""
    bench = load_script(ROOT / "bench" / "diffuser_conditioning.py", "bench_diffuser_conditioning_edit")
    trajs, returns, ids, diffuser, model = _toy_run()
    kw = dict(per_block=3, sampler="ddim", steps=10, guidance=1.2, seed=0, returns=returns, reward_fn=toy_reward,
              top_block=True)
    fresh = bench.evaluate(diffuser, model, trajs, returns, ids, **kw)
    edit = bench.evaluate(diffuser, model, trajs, returns, ids, strength=0.1, **kw)
    held = bench.evaluate(diffuser, model, trajs, returns, ids, inpaint_start=True, **kw)
    # an untrained model's fresh samples are far from every condition; a light edit stays by its own
    assert edit["trajectory_gap"]["own"] < 0.25 * edit["trajectory_gap"]["other"], edit["trajectory_gap"]
    assert fresh["trajectory_gap"]["own"] > 0.5 * fresh["trajectory_gap"]["other"], fresh["trajectory_gap"]
    assert held["start_gap"]["z_own"] == pytest.approx(0.0, abs=1e-5)
    assert fresh["start_gap"]["z_own"] > 0.1


def test_summarize_names_a_file_that_is_not_a_conditioning_result(tmp_path):
    bench = load_script(ROOT / "bench" / "diffuser_conditioning.py", "bench_diffuser_conditioning_bad")
    bad = tmp_path / "other-bench.json"
    bad.write_text(json.dumps({"evaluations": [{"step": 0}]}))  # no per-block statistics
    with pytest.raises(ValueError, match="other-bench.json: not a diffuser_conditioning results file"):
        bench.summarize([bad])
    broken = tmp_path / "cut.json"
    broken.write_text('{"evaluations": [')  # a write cut short
    with pytest.raises(ValueError, match="cut.json: not a diffuser_conditioning results file"):
        bench.summarize([broken])
