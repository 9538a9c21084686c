"""Locomotion datasets from our own SAC behaviour policies (torchrl_ftb.datasets.locomotion)."""
import json

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector

from torchrl_ftb.data import trajectories_to_flat, validate_trajectories
from torchrl_ftb.datasets.locomotion import (
    POLICY_DIR,
    collect_rollouts,
    compact_replay,
    evaluate_policy,
    load_behavior_policy,
    make_behavior_actor,
    make_behavior_env,
    make_locomotion_dataset,
    resimulate_replay,
    return_stats,
    save_behavior_policy,
    select_medium_checkpoint,
    shipped_policy_path,
)
from torchrl_ftb.datasets.registry import get_dataset_generator
from torchrl_ftb.envs import locomotion_true_reward

SHIPPED_ENVS = ("hopper", "walker2d", "halfcheetah")


@pytest.fixture(scope="module")
def random_replay():
    """A short SAC-style replay buffer (untrained actor) with float64 simulator states."""
    torch.manual_seed(0)
    env = make_behavior_env("hopper", seed=3, state_dtype=torch.float64)
    actor = make_behavior_actor(obs_dim=11, action_dim=3, num_cells=(16,))
    collector = Collector(env, actor, frames_per_batch=600, total_frames=600, auto_register_policy_transforms=False)
    flat = torch.cat([data.reshape(-1) for data in collector])
    collector.shutdown()
    return flat


def test_compact_replay_resimulates_the_buffer_exactly(random_replay):
    flat = random_replay
    done = flat["next", "done"].squeeze(-1)
    cut = next(i for i in range(550, 600) if not bool(done[i - 1]))  # cut inside an episode
    compact = compact_replay(flat, env="hopper", num_frames=cut)
    assert compact["actions"].shape == (cut, 3) and int(compact["lengths"].sum()) == cut
    td, check = resimulate_replay(compact, progress=False)
    validate_trajectories(td, obs_dim=11, action_dim=3)
    assert check["early_terminations"] == 0 and check["max_return_error"] < 1e-3
    got = trajectories_to_flat(td)
    assert torch.equal(got["observation"], flat["observation"][:cut])
    assert torch.equal(got["next", "observation"], flat["next", "observation"][:cut])
    assert torch.allclose(got["next", "reward"], flat["next", "reward"][:cut], atol=1e-6)
    assert torch.equal(got["state"], flat["state"][:cut].float())
    assert torch.equal(got["next", "terminated"], flat["next", "terminated"][:cut])
    last = td[-1][td[-1]["mask"]]  # the cut episode: truncated, not terminated
    assert bool(last["next", "truncated"][-1]) and not bool(last["next", "terminated"][-1])
    assert not bool((td["next", "terminated"] & td["next", "truncated"]).any())


def test_compact_replay_rejects_float32_state(random_replay):
    bad = random_replay.clone()
    bad.set("state", bad["state"].float())
    with pytest.raises(ValueError, match="float64"):
        compact_replay(bad, env="hopper", num_frames=100)
    with pytest.raises(ValueError, match="num_frames"):
        compact_replay(random_replay, env="hopper", num_frames=10**6)


def test_collect_rollouts_layout_and_true_reward():
    actor = make_behavior_actor(obs_dim=17, action_dim=6, num_cells=(16,))
    td = collect_rollouts(actor, "walker2d", num_transitions=60, max_episode_steps=25, num_envs=4,
                          seed=1, progress=False)
    validate_trajectories(td, obs_dim=17, action_dim=6)
    mask = td["mask"]
    assert int(mask.sum()) >= 60 and int(mask.sum(-1).max()) <= 25
    last = mask.sum(-1) - 1
    rows = torch.arange(td.shape[0])
    term, trunc = td["next", "terminated"].squeeze(-1), td["next", "truncated"].squeeze(-1)
    # every episode ends exactly once, time limits are truncation, never both
    assert bool((term | trunc)[rows, last].all())
    assert int((term | trunc).sum()) == td.shape[0]
    assert not bool((term & trunc).any())
    assert bool(trunc[rows, last][mask.sum(-1) < 25].logical_not().all())
    # state = qpos || qvel, consistent with the observation (qpos[1:], qvel)
    valid = td[mask]
    assert torch.allclose(valid["observation"][:, :8], valid["state"][:, 1:9])
    assert torch.allclose(valid["observation"][:, 8:], valid["state"][:, 9:].clamp(-10, 10), atol=1e-5)
    # rewards are the env's: checked with the envs-stage oracle (exact where no velocity
    # was clipped in the observation)
    exact = valid[valid["state"][:, 9:].abs().amax(-1) < 9.9][:10]
    assert exact.shape[0] >= 3
    r = locomotion_true_reward("walker2d", exact["observation"], exact["action"])
    assert torch.allclose(r, exact["next", "reward"], atol=1e-3)
    # seeded: same seed, same data
    again = collect_rollouts(actor, "walker2d", num_transitions=60, max_episode_steps=25, num_envs=4,
                             seed=1, progress=False)
    assert torch.equal(again["action"], td["action"])


def test_select_medium_checkpoint_and_errors(tmp_path):
    assert select_medium_checkpoint([10.0, 400.0, 1200.0, 3000.0, 2500.0]) == (2, 3)
    assert select_medium_checkpoint([-5.0, 3.0]) == (1, 1)
    assert select_medium_checkpoint([-50.0, -20.0, -30.0]) == (1, 1)
    with pytest.raises(ValueError):
        select_medium_checkpoint([])
    with pytest.raises(FileNotFoundError):
        load_behavior_policy(tmp_path / "missing.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="bad.pt"):
        load_behavior_policy(tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="unknown locomotion dataset"):
        make_locomotion_dataset("hopper-expert-replay", cache_dir=tmp_path)
    assert get_dataset_generator("walker2d-medium-replay").name == "locomotion"
    assert get_dataset_generator("hopper-medium-expert-v2").name == "locomotion"


def test_save_load_behavior_policy_roundtrip(tmp_path):
    actor = make_behavior_actor(obs_dim=11, action_dim=3, num_cells=(8, 8))
    cfg = {"env_name": "Hopper-v5", "obs_dim": 11, "action_dim": 3, "num_cells": [8, 8]}
    path = save_behavior_policy(actor, tmp_path / "p.pt", config=cfg, frames=7, eval_return=1.5)
    torch.load(path, weights_only=True)  # plain tensors and values only
    loaded, info = load_behavior_policy(path)
    obs = TensorDict({"observation": torch.randn(5, 11)}, [5])
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(actor(obs.clone())["action"], loaded(obs.clone())["action"])
    assert info["frames"] == 7 and info["eval_return"] == 1.5


@pytest.mark.parametrize("env", SHIPPED_ENVS)
def test_shipped_policies_load_act_and_beat_random(env):
    record = json.loads((POLICY_DIR / f"{env}_policies.json").read_text())
    for which in ("medium", "expert"):
        path = shipped_policy_path(env, which)
        assert path.stat().st_size < 1_000_000
        assert "actor" in torch.load(path, weights_only=True)
    expert, info = load_behavior_policy(shipped_policy_path(env, "expert"))
    medium, _ = load_behavior_policy(shipped_policy_path(env, "medium"))
    assert info["env_name"] == record["env_id"]
    pol = record["policies"]
    assert pol["expert"]["train_eval_return"] >= pol["medium"]["train_eval_return"]
    # acts in the env, inside the action bounds, and does better than an untrained actor
    untrained = make_behavior_actor(obs_dim=info["obs_dim"], action_dim=info["action_dim"])
    steps = 150
    ret_expert = evaluate_policy(expert, env, episodes=2, seed=5, max_steps=steps)
    ret_random = evaluate_policy(untrained, env, episodes=2, seed=5, max_steps=steps)
    assert min(ret_expert) > max(ret_random)
    td = collect_rollouts(medium, env, num_transitions=20, max_episode_steps=20, num_envs=1, progress=False)
    assert bool((td["action"].abs() <= 1).all())


@pytest.mark.parametrize("env", SHIPPED_ENVS)
def test_shipped_medium_replay_resimulates(env):
    record = json.loads((POLICY_DIR / f"{env}_policies.json").read_text())["medium_replay"]
    compact = torch.load(POLICY_DIR / record["file"], weights_only=True)
    assert compact["num_frames"] == record["frames"]
    n = 30  # the first episodes (the full buffer is checked by export_behavior_policies)
    td, check = resimulate_replay(compact, max_episodes=n, progress=False)
    returns = (td["next", "reward"].squeeze(-1) * td["mask"]).sum(-1)
    assert torch.allclose(returns, compact["returns"][:n], atol=1e-2)
    assert check["early_terminations"] == 0
    assert record["resimulation_check"]["max_observation_error"] < 1e-5  # float32 rounding at most


def test_make_medium_expert_dataset_groups_and_cache(tmp_path):
    td, meta = make_locomotion_dataset("hopper-medium-expert", num_transitions=2000, seed=0,
                                       cache_dir=tmp_path, progress=False)
    validate_trajectories(td, obs_dim=11, action_dim=3)
    group = meta["per_trajectory"]["group"]
    assert meta["groups"] == ["medium", "expert"] and set(group.tolist()) == {0, 1}
    import importlib.metadata  # the simulator's build is part of the cache key: another build, another dataset

    assert meta["mujoco_version"] == importlib.metadata.version("mujoco") and "gymnasium_version" in meta
    ret = (td["next", "reward"].squeeze(-1) * td["mask"]).sum(-1)
    # the expert half is better than the medium half (what makes medium-expert useful)
    assert float(ret[group == 1].mean()) > float(ret[group == 0].mean())
    stats = return_stats(td, env="hopper")
    assert meta["stats"]["transitions"] == stats["transitions"] >= 2000
    assert stats["return_min"] <= stats["return_median"] <= stats["return_max"]
    assert "d4rl_score_median_approx" in stats
    # time limits are truncation, never termination
    at_limit = td["mask"].sum(-1) == 1000
    if bool(at_limit.any()):
        assert not bool(td["next", "terminated"][at_limit].any())
    # cached: same folder, same data, no regeneration
    td2, meta2 = make_locomotion_dataset("hopper-medium-expert", num_transitions=2000, seed=0,
                                         cache_dir=tmp_path, progress=False)
    assert meta2["path"] == meta["path"] and torch.equal(td2["observation"], td["observation"])
    assert meta2["generation_seconds"] == meta["generation_seconds"]


def _recorded_and_a_falling_claim() -> tuple[TensorDict, TensorDict, float]:
    """A recorded hopper trajectory (random actions: it falls within ~15 steps), padded to 200 steps, and a
    "generated" one that claims to stand at its start for 200 steps while pushing full torque: every transition's
    own reward is healthy, but its actions make the hopper fall in ~20 steps. Returns (final set, top-k, recorded
    return)."""
    from torchrl_ftb.envs import make_locomotion_env

    horizon = 200
    rec = make_locomotion_env("hopper", seed=0).rollout(horizon)
    n = rec.batch_size[0]
    recorded = TensorDict({"observation": torch.zeros(1, horizon, 11), "action": torch.zeros(1, horizon, 3),
                           "mask": torch.zeros(1, horizon, dtype=torch.bool)}, [1, horizon])
    recorded["observation"][0, :n], recorded["action"][0, :n], recorded["mask"][0, :n] = (
        rec["observation"], rec["action"], True)
    standing = TensorDict({"observation": rec["observation"][:1].expand(horizon, 11).unsqueeze(0).clone(),
                           "action": torch.ones(1, horizon, 3), "mask": torch.ones(1, horizon, dtype=torch.bool)},
                          [1, horizon])
    return torch.cat([recorded, standing]), recorded, float(rec["next", "reward"].sum())


def test_locomotion_open_loop_replays_recorded_and_catches_a_claimed_path_that_falls():
    from torchrl_ftb.analysis import locomotion_open_loop_improvement

    final, recorded, recorded_return = _recorded_and_a_falling_claim()
    out = locomotion_open_loop_improvement(final, recorded, torch.tensor([False, True]), env_name="hopper")
    imp = out["improvement"]["plain"]
    assert imp["replayed"]["true_return_mean_before"] == pytest.approx(recorded_return, abs=1e-3)
    assert imp["claimed"]["true_return_mean_before"] == pytest.approx(recorded_return, abs=1e-3)
    (sample,) = out["samples"]
    assert sample["replay_terminated"] and sample["replay_length"] < 50 and sample["length"] == 200
    assert sample["claimed_plain"] > 150 and sample["replayed_plain"] < 0.5 * sample["claimed_plain"]
    assert imp["claimed"]["true_return_max_after"] == pytest.approx(sample["claimed_plain"])
    assert imp["replayed"]["true_return_max_after"] < imp["claimed"]["true_return_max_after"]
    assert out["replay_terminated_rate"] == 1.0 and out["num_generated"] == 1
    with pytest.raises(ValueError, match=r"generated has shape \[1\], expected \[2\]"):
        locomotion_open_loop_improvement(final, recorded, torch.tensor([True]), env_name="hopper")


def test_recipe_open_loop_analysis_on_locomotion(tmp_path, report_rows):
    import types
    from pathlib import Path

    from omegaconf import OmegaConf

    from torchrl_ftb.analysis import locomotion_open_loop_improvement
    from torchrl_ftb.testing import load_script

    final, recorded, _ = _recorded_and_a_falling_claim()
    out = locomotion_open_loop_improvement(final, recorded, torch.tensor([False, True]), env_name="hopper")
    recipe = load_script(Path(__file__).resolve().parents[1] / "recipes" / "ftb_offline.py", "recipe_open_loop_loco")
    cfg = OmegaConf.create({"env": {"name": "hopper"}, "flow": {}, "analysis": {"open_loop": True}})
    run = types.SimpleNamespace(path=tmp_path)
    flow = {"trajectories": final, "original": recorded, "source_step": torch.tensor([0, 2])}
    ours = recipe.open_loop_analysis(cfg, run, flow, None, {"domain": "locomotion"}, progress=False)
    assert ours["improvement"] == out["improvement"] and "samples" not in ours
    saved = json.loads((tmp_path / "open_loop.json").read_text())
    assert [s["replay_terminated"] for s in saved["samples"]] == [True]
    assert (tmp_path / "plots" / "open_loop_claimed_vs_replayed.png").stat().st_size > 0
    table = report_rows(recipe, analysis={"open_loop": ours}, env="hopper")
    r = out["improvement"]["plain"]["replayed"]
    assert table["true return top-k replayed open loop in the simulator: mean / max before -> after"] == (
        f"{r['true_return_mean_before']:.4g} -> {r['true_return_mean_after']:.4g} / "
        f"{r['true_return_max_before']:.4g} -> {r['true_return_max_after']:.4g}")
    row = table["generated in final set, replayed: return claimed -> replayed (replays the env ends early; median "
                "share of steps run)"]
    assert row.startswith(f"{ours['claimed_plain_mean_generated']:.4g} -> ") and row.endswith(
        f"(1; {ours['replay_length_fraction_median']:.4g})")
    # hopper reproduces its recorded top-k from the observations: the fidelity row's two numbers agree
    fidelity = table["simulator on the top-k's own actions: recorded -> replayed mean (equal: the data reproduced)"]
    recorded_mean, replayed_mean = (float(x) for x in fidelity.split(" -> "))
    assert replayed_mean == pytest.approx(recorded_mean, rel=1e-3)


def test_open_loop_bench_on_a_locomotion_run(tmp_path):
    """bench/open_loop.py on a finished locomotion run: the library's reading, and the top-k's own actions replayed
    with noise (std 0: the recorded return)."""
    from pathlib import Path

    from omegaconf import OmegaConf

    from torchrl_ftb.testing import load_script

    final, recorded, recorded_return = _recorded_and_a_falling_claim()
    (tmp_path / "checkpoints").mkdir()
    OmegaConf.save(OmegaConf.create({"env": {"name": "hopper"}, "seed": 3, "flow": {}}), tmp_path / "config.yaml")
    torch.save({"trajectories": {"data": final.to_dict(), "batch_size": list(final.batch_size)},
                "original": {"data": recorded.to_dict(), "batch_size": list(recorded.batch_size)},
                "source_step": torch.tensor([0, 2])}, tmp_path / "checkpoints" / "flow.pt")
    bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "open_loop.py", "bench_open_loop_loco")
    entry = bench.locomotion_open_loop(tmp_path, noise=[0.0, 0.5], progress=False)
    assert entry["env"] == "hopper" and entry["seed"] == 3 and entry["num_generated"] == 1
    assert entry["improvement"]["plain"]["replayed"]["true_return_mean_before"] == pytest.approx(recorded_return, abs=1e-3)
    clean, noisy = entry["top_k_action_noise"]
    assert clean["return_mean"] == pytest.approx(recorded_return, abs=1e-3) and clean["terminated_early"] == 0.0
    assert noisy["action_noise_std"] == 0.5 and noisy["return_mean"] != clean["return_mean"]
    assert "N(0, 0.5)" in bench.describe(tmp_path, entry)


def test_locomotion_tracker_reproduces_a_recorded_path_and_tells_reachable_from_unreachable_claims(tmp_path,
                                                                                                     report_rows):
    """The shooting tracker follows a recorded path exactly. The claimed standing path, whose own actions fall
    open loop, is a reachable path: other actions hold it, so its tracked return is near its claim. A path that
    claims a fast forward velocity while staying in place is not: tracked far below its claim. The recipe's
    analysis.tracked writes the same numbers and its report rows."""
    import types
    from pathlib import Path

    from omegaconf import OmegaConf

    from torchrl_ftb.analysis import locomotion_open_loop_improvement, locomotion_tracked_improvement
    from torchrl_ftb.testing import load_script

    final, recorded, recorded_return = _recorded_and_a_falling_claim()
    sliding = final[1:].clone()
    sliding["observation"][..., 5] = 3.0  # x velocity 3 m/s, the body never moving: each transition earns it
    final = torch.cat([final, sliding])
    generated = torch.tensor([False, True, True])
    out = locomotion_tracked_improvement(final, recorded, generated, env_name="hopper", candidates=32)
    assert out["tracked"]["true_return_mean_before"] == pytest.approx(recorded_return, abs=1e-3)
    assert out["fidelity"]["path_error_median"] < 1e-4
    standing, slide = out["samples"]
    open_loop = locomotion_open_loop_improvement(final, recorded, generated, env_name="hopper")["samples"][0]
    assert open_loop["replay_terminated"] and not standing["tracked_terminated"]
    assert standing["tracked_plain"] == pytest.approx(standing["claimed_plain"], rel=0.15)
    assert slide["claimed_plain"] > 2 * standing["claimed_plain"] and slide["tracked_plain"] < 0.6 * slide["claimed_plain"]
    assert slide["path_error"] > standing["path_error"]
    recipe = load_script(Path(__file__).resolve().parents[1] / "recipes" / "ftb_offline.py", "recipe_tracked_loco")
    cfg = OmegaConf.create({"env": {"name": "hopper"}, "seed": 0, "flow": {}, "analysis": {"tracked": True}})
    flow = {"trajectories": final, "original": recorded, "source_step": torch.tensor([0, 2, 2])}
    ours = recipe.tracked_analysis(cfg, types.SimpleNamespace(path=tmp_path), flow, None, {"domain": "locomotion"},
                                   progress=False)
    assert ours["tracked"]["true_return_mean_before"] == pytest.approx(recorded_return, abs=1e-3)
    assert len(json.loads((tmp_path / "tracked.json").read_text())["samples"]) == 2
    table = report_rows(recipe, analysis={"tracked": ours}, env="hopper")
    assert "true return top-k tracked in closed loop (simulator shooting tracker): mean / max before -> after" in table
    assert table["tracker on the top-k: claimed -> tracked mean (scaled path error, median)"].startswith(
        f"{recorded_return:.4g} -> {recorded_return:.4g}")


def test_dynamics_oracle_scores_a_recorded_path_valid_and_a_claimed_one_not():
    """The recipe's validity analysis on locomotion: a recorded hopper trajectory obeys the simulator's one-step
    dynamics (error ~0), the claimed standing path under full torque does not."""
    from torchrl_ftb.analysis import dynamics_error
    from torchrl_ftb.envs import dynamics_oracle

    final, recorded, _ = _recorded_and_a_falling_claim()
    oracle = dynamics_oracle("hopper")
    assert dynamics_error(recorded, oracle)["mean"] < 1e-4
    assert dynamics_error(final[1:], oracle)["mean"] > 1e-2


def test_lookahead_tracker_reproduces_a_recorded_path_and_is_checked(report_rows):
    """With a lookahead the shooting tracker still reproduces a recorded path exactly (its own actions score 0 over
    every lookahead step); the recipe checks the option at start and names it in the report row."""
    from pathlib import Path

    from omegaconf import OmegaConf

    from torchrl_ftb.analysis import locomotion_tracked_improvement, track_top_k
    from torchrl_ftb.envs import track_locomotion_paths
    from torchrl_ftb.testing import load_script

    final, recorded, recorded_return = _recorded_and_a_falling_claim()
    out = locomotion_tracked_improvement(final, recorded, torch.tensor([False, True]), env_name="hopper",
                                         candidates=8, lookahead=4)
    assert out["lookahead"] == 4
    assert out["tracked"]["true_return_mean_before"] == pytest.approx(recorded_return, abs=1e-3)
    assert out["fidelity"]["path_error_median"] < 1e-4
    # the top-k tracked once and handed in reads the same (what bench/supplement_readings.py does per supplement)
    top = track_top_k("hopper", recorded, candidates=8, lookahead=4)
    again = locomotion_tracked_improvement(final, recorded, torch.tensor([False, True]), env_name="hopper",
                                           candidates=8, lookahead=4, original_tracked=top)
    assert again == out
    # ... and one tracked with other options, or from other trajectories, is refused
    with pytest.raises(ValueError, match="other options: candidates=8 there, 64 here, lookahead=4 there, 1 here"):
        locomotion_tracked_improvement(final, recorded, torch.tensor([False, True]), env_name="hopper",
                                       original_tracked=top)
    with pytest.raises(ValueError, match="other options: seed=0 there, 1 here"):
        locomotion_tracked_improvement(final, recorded, torch.tensor([False, True]), env_name="hopper",
                                       candidates=8, lookahead=4, seed=1, original_tracked=top)
    with pytest.raises(ValueError, match="tracked from other trajectories"):
        locomotion_tracked_improvement(recorded, final[1:], torch.tensor([False]), env_name="hopper",
                                       candidates=8, lookahead=4, original_tracked=top)
    shorter = recorded.clone()
    shorter["mask"][0, int(shorter["mask"][0].sum()) - 1] = False  # its last valid step dropped
    with pytest.raises(ValueError, match="their observations or masks differ"):
        locomotion_tracked_improvement(shorter, shorter, torch.tensor([False]), env_name="hopper",
                                       candidates=8, lookahead=4, original_tracked=top)
    with pytest.raises(TypeError, match="must be a TrackedTopK"):
        locomotion_tracked_improvement(final, recorded, torch.tensor([False, True]), env_name="hopper",
                                       candidates=8, lookahead=4, original_tracked=tuple(top)[:2])
    with pytest.raises(ValueError, match="lookahead >= 1"):
        track_locomotion_paths("hopper", recorded["observation"], recorded["action"], [10], lookahead=0)
    recipe = load_script(Path(__file__).resolve().parents[1] / "recipes" / "ftb_offline.py", "recipe_lookahead")
    with pytest.raises(ValueError, match="tracker.lookahead=0"):
        recipe.tracker_lookahead(OmegaConf.create({"tracker": {"lookahead": 0}}))
    assert recipe.tracker_lookahead(OmegaConf.create({})) == 1
    table = report_rows(recipe, analysis={"tracked": out}, env="hopper")
    assert "true return top-k tracked in closed loop (simulator shooting tracker, 4-step lookahead): mean / max " \
           "before -> after" in table


def test_simulator_readings_depend_on_the_path_alone():
    """A path's open-loop replay and its tracked reading are the same alone or after another path (a fresh solver
    warm start per episode, perturbations seeded by the path's own numbers): a trajectory kept from the top-k in the
    final set reads the same in both sets."""
    from torchrl_ftb.envs import make_locomotion_env, replay_locomotion_actions, track_locomotion_paths

    torch.manual_seed(0)
    a, b = (make_locomotion_env("halfcheetah", seed=s).rollout(120) for s in (0, 1))

    def readings(tds):
        obs, act = torch.stack([t["observation"] for t in tds]), torch.stack([t["action"] for t in tds])
        replay = replay_locomotion_actions("halfcheetah", obs[:, 0], list(act))
        track = track_locomotion_paths("halfcheetah", obs, act, [120] * len(tds), candidates=6, lookahead=2)
        return float(replay[-1]["reward"].sum()), float(track[-1]["reward"].sum())

    assert readings([b]) == readings([a, b])


def test_fidelity_bench_rereads_hopper_data_exactly(tmp_path):
    """bench/locomotion_fidelity.py: Hopper's recorded trajectories replay to their recorded returns from their first
    observation, from the stored state, and after another trajectory (Hopper's readings are exact)."""
    from pathlib import Path

    from torchrl_ftb.testing import load_script

    bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "locomotion_fidelity.py", "bench_fidelity")
    rows = bench.fidelity("hopper-medium-replay", 2, cache_dir=tmp_path)
    assert len(rows) == 2
    for r in rows:
        for key in ("from_observation", "from_stored_state", "from_observation_after_another"):
            assert r[key] == pytest.approx(r["recorded"], abs=1e-2), key


def test_supplement_readings_bench_tracks_the_top_k_once(tmp_path):
    """bench/supplement_readings.py tracks the top-k once for all supplements: a reading given that tracking equals
    one that tracks the top-k itself, and a supplement of another horizon is refused naming its file."""
    from pathlib import Path

    from torchrl_ftb.augmentation.augment import SUPPLEMENT_FORMAT
    from torchrl_ftb.data.trajectories import atomic_torch_save
    from torchrl_ftb.testing import load_script

    bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "supplement_readings.py", "bench_supplement")
    final, recorded, _ = _recorded_and_a_falling_claim()
    final[("next", "reward")] = torch.zeros(*final.batch_size, 1)
    path = tmp_path / "supplement.pt"
    atomic_torch_save({"format": SUPPLEMENT_FORMAT, "data": final.to_dict(), "batch_size": list(final.batch_size),
                       "info": {"kind": "ftb"}}, path)
    top_tracked = bench.track_top("hopper-medium-replay", recorded, candidates=8, seed=0)
    once = bench.readings("hopper-medium-replay", recorded, path, candidates=8, seed=0, top_tracked=top_tracked)
    assert once == bench.readings("hopper-medium-replay", recorded, path, candidates=8, seed=0)
    assert once["top_k"] == 1 and once["num_trajectories"] == 2 and once["kind"] == "ftb"
    short = tmp_path / "short.pt"
    atomic_torch_save({"format": SUPPLEMENT_FORMAT, "data": final[:, :50].to_dict(), "batch_size": [2, 50],
                       "info": {}}, short)
    with pytest.raises(ValueError, match="short.pt: horizon 50 != the dataset's 200"):
        bench.readings("hopper-medium-replay", recorded, short, candidates=8, seed=0)


def test_shoot_keeps_the_nearest_try_never_a_nan_and_restores_the_state():
    """``shoot`` (one shooting step, shared by both trackers): the least distance wins (the first among equals, or
    within the tolerance), a NaN distance (a simulation gone unstable) is never kept, and every try starts from,
    and the simulator ends in, the state it was given."""
    import gymnasium as gym
    import numpy as np

    from torchrl_ftb.envs.sim_state import save_sim_state, shoot

    u = gym.make("Hopper-v5").unwrapped
    u.reset(seed=0)
    before = save_sim_state(u)
    starts = []

    def rollout(dists):
        def run(j, a):
            starts.append(save_sim_state(u).copy())
            u.do_simulation(a, u.frame_skip)  # moves the simulator: the next try must not start from here
            return dists[j]
        return run

    tries = np.zeros((4, 3))
    assert shoot(u, tries, rollout([3.0, 1.0, 1.0, 2.0])) == 1
    assert all((s == before).all() for s in starts) and (save_sim_state(u) == before).all()
    assert shoot(u, tries, rollout([float("nan"), 2.0, float("nan"), 1.0])) == 3
    assert shoot(u, tries, rollout([float("nan")] * 4)) == 0
    assert shoot(u, tries, rollout([1.0, 0.95, 0.5, 0.9]), tolerance=0.1) == 2  # 0.95 and 0.9: within 0.1 of 1
    assert shoot(u, tries, rollout([1.0, 0.95, 0.92, 0.91]), tolerance=0.1) == 0
