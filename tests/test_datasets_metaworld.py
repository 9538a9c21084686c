"""Tests of the Meta-World dataset generator (IPL recipe), its cache, stats, registry and CLI."""
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from torchrl_ftb.data import success_streak_length, validate_trajectories
from torchrl_ftb.datasets import (
    GROUPS,
    dataset_stats,
    format_stats,
    get_dataset_generator,
    make_metaworld_dataset,
)
from torchrl_ftb.datasets.metaworld import ACTION_CLIP, SUCCESS_STREAK, default_cache_dir
from torchrl_ftb.testing import load_script, make_toy_dataset


def test_registry_finds_metaworld_and_rejects_unknown():
    assert get_dataset_generator("drawer-open-v3").name == "metaworld"
    with pytest.raises(ValueError, match="no dataset generator"):
        get_dataset_generator("not-an-env-v0")


def test_bad_options_raise():
    with pytest.raises(ValueError, match="valid v3 tasks"):
        make_metaworld_dataset("button-press")
    with pytest.raises(ValueError, match="episodes_per_group"):
        make_metaworld_dataset("button-press-v3", episodes_per_group=0)
    with pytest.raises(ValueError, match=r"groups: unknown group\(s\) \['experts'\]"):
        make_metaworld_dataset("button-press-v3", groups=["experts"])
    with pytest.raises(ValueError, match="groups: need one or more distinct"):
        make_metaworld_dataset("button-press-v3", groups=["random", "random"])
    with pytest.raises(ValueError, match="groups: need one or more distinct"):
        make_metaworld_dataset("button-press-v3", groups=[])


def test_recipe_section_passes_groups_to_the_metaworld_generator():
    from torchrl_ftb.datasets import dataset_kwargs

    section = {"seed": 0, "episodes_per_group": 2, "noise": 3.0, "groups": ["expert", "random"], "options": {}}
    kw = dataset_kwargs("button-press-v3", section, max_episode_steps=50, progress=False)
    assert kw["groups"] == ["expert", "random"] and kw["noise"] == 3.0 and kw["max_steps"] == 50
    assert "groups" not in dataset_kwargs("button-press-v3", {**section, "groups": None}, progress=False)


def test_cache_dir_env_override(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCHRL_FTB_DATA", str(tmp_path))
    assert default_cache_dir() == tmp_path


def test_dataset_stats_matches_manual_computation():
    td = make_toy_dataset(num_trajectories=6, horizon=10, seed=1)
    per = TensorDict({"group": torch.tensor([0, 0, 1, 1, 1, 0])}, batch_size=[6])
    stats = dataset_stats(td, per, groups=["a", "b"])
    sel = per["group"] == 1
    ret = (td["next", "reward"].squeeze(-1) * td["mask"]).sum(-1)
    assert stats["b"]["episodes"] == 3 and stats["all"]["episodes"] == 6
    assert stats["b"]["mean_return"] == pytest.approx(float(ret[sel].mean()), rel=1e-5)
    assert stats["b"]["mean_length"] == pytest.approx(float(td["mask"][sel].sum(-1).float().mean()))
    succ = td["next", "success"].squeeze(-1).any(-1).float()
    assert stats["a"]["success_rate"] == pytest.approx(float(succ[~sel].mean()))
    assert "mean_return" in format_stats(stats)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    """1 noiseless episode per group, horizon 150 (the expert succeeds and stops early)."""
    cache = tmp_path_factory.mktemp("mw_cache")
    td, meta = make_metaworld_dataset("button-press-v3", episodes_per_group=1, noise=0.0, seed=0,
                                      max_steps=150, cache_dir=cache, progress=False)
    return td, meta, cache


@pytest.mark.integration
def test_generated_dataset_follows_conventions_and_recipe(tiny_dataset):
    td, meta, _ = tiny_dataset
    assert td.batch_size == (len(GROUPS), 150)
    validate_trajectories(td, obs_dim=39, action_dim=4, require=[("next", "reward"), ("next", "success"), "state"])
    per = meta["per_trajectory"]
    assert per["group"].tolist() == [0, 1, 2, 3] and meta["groups"] == list(GROUPS)
    assert meta["noise"] == 0.0 and meta["task"] == "button-press-v3" and meta["generator_version"] >= 1
    mask = td["mask"]
    assert float(td["action"][mask].abs().max()) <= ACTION_CLIP
    assert td["state"].shape[-1] == meta["state_dim"] and float(td["state"][mask].abs().sum()) > 0
    # expert: succeeds, then stops after exactly SUCCESS_STREAK consecutive success steps (truncated)
    length = int(mask[0].sum())
    succ = td["next", "success"][0, :length, 0]
    assert length < 150 and bool(succ[-SUCCESS_STREAK:].all()) and not bool(succ[-SUCCESS_STREAK - 1])
    assert bool(td["next", "truncated"][0, length - 1]) and not bool(td["next", "terminated"].any())
    # success_streak_length is the generator's stop rule: on recorded episodes it cuts nothing
    cut = success_streak_length(td["next", "success"][..., 0], mask, streak=SUCCESS_STREAK)
    assert cut.tolist() == mask.sum(-1).tolist()
    # ... and on an episode run on past its streak (as a generated one may be) it cuts where the data stop
    longer = torch.cat([td["next", "success"][0, :length, 0], torch.ones(10, dtype=torch.bool)])
    assert int(success_streak_length(longer[None], torch.ones(1, length + 10, dtype=torch.bool),
                                     streak=SUCCESS_STREAK)) == length
    assert int(td["next", "done"].sum()) == len(GROUPS)  # one end per episode
    # the random group does not solve the task and runs to the time limit
    assert int(mask[2].sum()) == 150
    # next observation of step h is the observation of step h + 1
    assert torch.equal(td["next", "observation"][:, :-1][mask[:, 1:]], td["observation"][:, 1:][mask[:, 1:]])
    # the cross-env episode is driven by another task's scripted policy
    assert per["policy_task"][3] >= 0 and per["policy_task"][3] != per["policy_task"][0] and per["policy_task"][2] == -1
    stats = dataset_stats(td, per)
    assert stats["expert"]["success_rate"] == 1.0 and stats["random"]["success_rate"] == 0.0


@pytest.mark.integration
def test_cache_reload_is_identical_and_config_changes_the_key(tiny_dataset):
    td, meta, cache = tiny_dataset
    td2, meta2 = make_metaworld_dataset("button-press-v3", episodes_per_group=1, noise=0.0, seed=0,
                                        max_steps=150, cache_dir=cache, progress=False)
    assert meta2["path"] == meta["path"] and (td2 == td).all()
    assert meta2["generation_seconds"] == meta["generation_seconds"]  # loaded, not regenerated
    td3, meta3 = make_metaworld_dataset("button-press-v3", episodes_per_group=1, noise=0.5, seed=0,
                                        max_steps=20, cache_dir=cache, progress=False)
    assert meta3["path"] != meta["path"] and td3.batch_size == (4, 20)
    # noise changes the expert's actions; the first observation (fixed goal, same seed) is the same
    assert torch.equal(td3["observation"][0, 0], td["observation"][0, 0])
    assert not torch.allclose(td3["action"][0, :20], td["action"][0, :20])


@pytest.mark.integration
def test_a_group_subset_holds_those_groups_episodes_of_the_full_dataset(tiny_dataset):
    td, meta, cache = tiny_dataset
    sub, smeta = make_metaworld_dataset("button-press-v3", episodes_per_group=1, noise=0.0, seed=0, max_steps=150,
                                        cache_dir=cache, progress=False, groups=("random", "expert"))
    assert smeta["groups"] == ["expert", "random"] and smeta["path"] != meta["path"]
    assert smeta["per_trajectory"]["group"].tolist() == [0, 1]  # indexes smeta["groups"]
    full_rows = [list(GROUPS).index("expert"), list(GROUPS).index("random")]
    assert (sub == td[full_rows]).all()
    stats = dataset_stats(sub, smeta["per_trajectory"], groups=smeta["groups"])
    assert set(stats) == {"expert", "random", "all"} and stats["expert"]["success_rate"] == 1.0
    # the full dataset's cache key is that of earlier versions: naming all four groups finds it
    _, again = make_metaworld_dataset("button-press-v3", episodes_per_group=1, noise=0.0, seed=0, max_steps=150,
                                      cache_dir=cache, progress=False, groups=list(reversed(GROUPS)))
    assert again["path"] == meta["path"]


@pytest.mark.integration
def test_make_dataset_cli_prints_group_stats(tiny_dataset, capsys):
    _, _, cache = tiny_dataset
    path = Path(__file__).parents[1] / "recipes" / "make_dataset.py"
    cli = load_script(path, "make_dataset_recipe")
    stats = cli.main(["--env", "button-press-v3", "--episodes-per-group", "1", "--noise", "0", "--seed", "0",
                      "--max-steps", "150", "--out", str(cache), "--no-progress"])
    out = capsys.readouterr().out
    assert set(stats) == {*GROUPS, "all"} and "expert" in out and stats["expert"]["success_rate"] == 1.0


@pytest.mark.integration
def test_expert_replay_keeps_each_episodes_goal_and_start(tiny_dataset):
    """generate_metaworld_episodes(expert=True) (bench/expert_headroom.py): every episode's own goal and
    start, acted on by the task's scripted expert; on the noiseless expert group it is the recorded episode."""
    from torchrl_ftb.datasets.metaworld import generate_metaworld_episodes

    td, meta, _ = tiny_dataset
    per = meta["per_trajectory"]
    jobs = list(zip(per["group"].tolist(), per["episode"].tolist()))
    eps = generate_metaworld_episodes("button-press-v3", jobs, seed=0, noise=0.0, max_steps=150, expert=True)
    first = torch.stack([torch.as_tensor(ep["observation"][0], dtype=torch.float32) for ep in eps])
    torch.testing.assert_close(first, td["observation"][:, 0])  # same goals and starts
    assert all(ep["policy_task"] == eps[0]["policy_task"] >= 0 for ep in eps)  # the task's expert everywhere
    assert all(bool(ep["success"].any()) for ep in eps)  # it solves the random and cross groups' goals too
    n = int(td["mask"][0].sum())
    assert len(eps[0]["reward"]) == n  # the expert group's episode, replayed exactly
    torch.testing.assert_close(torch.as_tensor(eps[0]["reward"], dtype=torch.float32), td["next", "reward"][0, :n, 0])
    assert not any(bool(td["next", "success"][i].any()) for i in (2,))  # the recorded random episode fails
    bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "expert_headroom.py", "bench_expert_headroom")
    mask = torch.tensor([[True, True, False], [True, True, True]])
    reward = torch.tensor([[1.0, 2.0, 9.0], [1.0, 1.0, 1.0]])[..., None]
    never = torch.zeros_like(reward, dtype=torch.bool)
    short = TensorDict({"mask": mask, "next": {"reward": reward, "terminated": never}}, batch_size=[2, 3])
    plain, filled = bench.returns(short, horizon=5)
    assert plain.tolist() == [3.0, 3.0] and filled.tolist() == [9.0, 5.0]  # the last reward, repeated to 5 steps
    from torchrl_ftb.analysis import match_rows

    assert match_rows(td["observation"][[2, 0]], td["observation"]).tolist() == [2, 0]
    with pytest.raises(ValueError, match="not rows of the dataset"):
        match_rows(td["observation"][[2, 0]] + 1.0, td["observation"])
    # bench/flow_generated.py's oracle returns: on recorded episodes, which end by the stop rule or at the
    # time limit (150 steps here, the fill's horizon), the stop-rule column equals the filled one, and the
    # oracle's plain / filled returns are the recorded ones (up to the rewarder's approximations)
    flow_bench = load_script(Path(__file__).resolve().parents[1] / "bench" / "flow_generated.py", "bench_flow_generated")
    oracle = flow_bench.metaworld_returns("button-press-v3", td, horizon=150)
    torch.testing.assert_close(oracle[:, 2], oracle[:, 1])
    assert bool((oracle[:, 1] > oracle[:, 0]).any())  # some episode stopped early and is filled
    recorded = torch.stack(bench.returns(td, horizon=150), -1)
    torch.testing.assert_close(oracle[:, :2], recorded, rtol=0.02, atol=0.0)


@pytest.mark.integration
def test_open_loop_replay_of_recorded_actions_reproduces_the_episodes(tiny_dataset):
    """replay_metaworld_actions: each episode's own goal and start, then given actions, open loop."""
    import numpy as np

    from torchrl_ftb.datasets.metaworld import replay_metaworld_actions

    td, meta, _ = tiny_dataset
    mask = td["mask"]
    jobs = [(int(g), int(e)) for g, e in zip(meta["per_trajectory"]["group"], meta["per_trajectory"]["episode"])]
    actions = [td["action"][i, :int(mask[i].sum())].numpy() for i in range(len(jobs))]
    eps = replay_metaworld_actions("button-press-v3", jobs, actions, seed=int(meta["seed"]), max_steps=150)
    for i, ep in enumerate(eps):
        n = int(mask[i].sum())
        assert len(ep["reward"]) == n  # the expert's replay stops at the same success streak
        np.testing.assert_allclose(ep["reward"], td["next", "reward"][i, :n, 0].numpy(), rtol=1e-5, atol=1e-5)
        assert ep["success"].tolist() == td["next", "success"][i, :n, 0].tolist()
    # other actions from the same start: the same first observation, another outcome; a short
    # sequence stops after its last action
    lazy = [np.zeros((40, 4))]
    other = replay_metaworld_actions("button-press-v3", jobs[:1], lazy, seed=int(meta["seed"]), max_steps=150)[0]
    np.testing.assert_allclose(other["observation"][0], td["observation"][0, 0].numpy(), atol=1e-6)
    assert len(other["reward"]) == 40 and not other["success"].any()
    with pytest.raises(ValueError, match=r"actions\[0\] has shape \[40\], expected \[L, 4\]"):
        replay_metaworld_actions("button-press-v3", jobs[:1], [np.zeros(40)], seed=0)
    with pytest.raises(ValueError, match="2 action sequences for 1 jobs"):
        replay_metaworld_actions("button-press-v3", jobs[:1], lazy * 2, seed=0)


def _fake_run_dir(td, cache, tmp_path):
    """A finished run directory on ``tiny_dataset`` whose final set's "generated" trajectories are its rows 0
    (expert, succeeds) and 2 (random), recorded ones: ``(repo root, cfg, dataset rows, final, original)``."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(config_dir=str(root / "recipes" / "config"), version_base="1.3"):
        cfg = compose(config_name="ftb_offline", overrides=[
            "env.name=button-press-v3", "env.max_episode_steps=150", "dataset.episodes_per_group=1",
            "dataset.noise=0.0", f"dataset.cache_dir={cache}", f"run_dir={tmp_path}"])
    (tmp_path / "checkpoints").mkdir()
    OmegaConf.save(cfg, tmp_path / "config.yaml", resolve=True)
    keep = td.select("observation", "action", "mask")
    final, original = keep[[0, 2, 1, 3]], keep[[1, 3, 0, 2]]
    torch.save({"trajectories": {"data": final.to_dict(), "batch_size": list(final.batch_size)},
                "original": {"data": original.to_dict(), "batch_size": list(original.batch_size)},
                "source_step": torch.tensor([1, 1, 0, 0])}, tmp_path / "checkpoints" / "flow.pt")
    return root, cfg, keep, final, original


@pytest.mark.integration
def test_nearest_start_finds_its_episode_when_the_hand_starts_off_the_common_start(tiny_dataset):
    """A generated sample's hand rarely starts exactly where every episode's does. The replay start must still be
    the episode whose object and goal the sample has: with a max-abs distance the hand offset tied every row and
    row 0 won (sessions 29-44 replayed 165 of 180 guidance-4 samples from row 0)."""
    from torchrl_ftb.analysis import nearest_start

    td, _, _ = tiny_dataset
    first = td["observation"][:, 0].float()
    hand_off = first.clone()
    hand_off[:, 0:3] += 0.3  # larger than any difference between the episodes' starts
    spread = (first[:, None] - first[None]).abs().amax(-1)
    assert float(spread.max()) < 0.3  # so under max-abs every row is 0.3 away: a tie
    rows, dist = nearest_start(hand_off, first)
    assert rows.tolist() == list(range(first.shape[0]))
    assert dist.tolist() == pytest.approx([0.3] * first.shape[0], abs=1e-6)


@pytest.mark.integration
def test_open_loop_bench_replays_recorded_trajectories_to_the_returns_read_off_their_states(tiny_dataset, tmp_path,
                                                                                           report_rows):
    """bench/open_loop.py end to end on a run directory whose "generated" trajectories are recorded ones:
    the simulator's replay and the reward read off the states agree, and each starts at its own episode."""
    import json
    import types

    from omegaconf import OmegaConf

    from torchrl_ftb.analysis import open_loop_improvement

    td, meta, cache = tiny_dataset
    root, cfg, keep, final, original = _fake_run_dir(td, cache, tmp_path)  # rows 0, 2 "generated"
    bench = load_script(root / "bench" / "open_loop.py", "bench_open_loop_mw")
    out = bench.open_loop(tmp_path, horizon=150, progress=False)
    assert out["num_generated"] == 2 and [s["start_row"] for s in out["samples"]] == [0, 2]
    from torchrl_ftb.data.labels import true_return

    plain, filled = true_return(td).double(), true_return(td, horizon=150).double()  # recorded rewards
    for s, row in zip(out["samples"], (0, 2)):
        assert s["start_distance"] == 0.0
        # the replay is the recorded episode; the return read off its states agrees up to the rewarder's
        # approximations (its last step's next observation is its own)
        assert s["replayed_stop_rule"] == pytest.approx(float(filled[row]), rel=1e-5)
        assert s["replayed_plain"] == pytest.approx(float(plain[row]), rel=1e-5)
        assert s["claimed_stop_rule"] == pytest.approx(s["replayed_stop_rule"], rel=0.02)
    assert [s["replay_success"] for s in out["samples"]] == [True, False]
    imp = out["improvement"]["stop_rule_150"]["replayed"]  # the same four trajectories before and after
    assert imp["true_return_mean_after"] == pytest.approx(imp["true_return_mean_before"], rel=1e-6)  # float32 data
    assert imp["true_return_max_after"] == pytest.approx(float(filled.max()), rel=1e-5)
    assert out["start_within_tolerance"] == 1.0 and out["replay_success_rate"] == 0.5
    assert out["start_hand_object_median"] == out["data_start_hand_object_median"] > 0  # the recorded starts
    # the recipe's analysis.open_loop: the same numbers, open_loop.json, a scatter plot and two report rows
    recipe = load_script(root / "recipes" / "ftb_offline.py", "recipe_open_loop_mw")
    run = types.SimpleNamespace(path=tmp_path)
    flow = {"trajectories": final, "original": original, "source_step": torch.tensor([1, 1, 0, 0]),
            "original_indices": torch.tensor([1, 3, 0, 2])}
    ours = recipe.open_loop_analysis(cfg, run, flow, td, meta, progress=False)
    assert ours["improvement"] == out["improvement"] and "samples" not in ours
    saved = json.loads((tmp_path / "open_loop.json").read_text())
    assert [s["start_row"] for s in saved["samples"]] == [0, 2]
    assert (tmp_path / "plots" / "open_loop_claimed_vs_replayed.png").stat().st_size > 0
    table = report_rows(recipe, analysis={"open_loop": ours})
    row = table["true return top-k replayed in the simulator (stop rule, 150 steps): mean / max before -> after"]
    assert row.endswith(f"/ {imp['true_return_max_before']:.4g} -> {imp['true_return_max_after']:.4g}")
    assert table["generated in final set, replayed: return claimed -> replayed (replays that succeed)"].endswith("(0.5)")
    assert table["generated in final set, first step: off the nearest dataset start, m (median) / hand-object "
                 "distance, m: sample vs that start"].startswith("0 / ")
    # off: no replay; data without goals and starts (toy): none either (locomotion: tests/test_locomotion.py)
    assert recipe.open_loop_analysis(OmegaConf.merge(cfg, {"analysis": {"open_loop": False}}), run, flow, td, meta,
                                     progress=False) is None
    assert recipe.open_loop_analysis(cfg, run, flow, td, {"domain": "toy"}, progress=False) is None
    with pytest.raises(ValueError, match="not a generated Meta-World one"):
        open_loop_improvement(final, original, torch.tensor([1, 1, 0, 0]) > 0, td, {"domain": "toy"},
                              task="button-press-v3", horizon=150)
    with pytest.raises(ValueError, match=r"generated has shape \[3\], expected \[4\]"):
        open_loop_improvement(final, original, torch.ones(3, dtype=torch.bool), td, meta,
                              task="button-press-v3", horizon=150)


@pytest.mark.integration
def test_tracked_replay_reads_both_sides_through_the_same_tracker(tiny_dataset, tmp_path, report_rows):
    """bench/tracked_replay.py (torchrl_ftb.analysis.tracked_improvement) and the recipe's analysis.tracked
    on a run directory whose "generated" trajectories are recorded ones: a generated path tracked from its
    own start is the same episode as its top-k twin, so top-k -> final is unchanged, and the fidelity
    compares with the recording."""
    import json

    from omegaconf import OmegaConf

    from torchrl_ftb.analysis import tracked_improvement
    from torchrl_ftb.policy import fit_path_tracker
    from torchrl_ftb.data.labels import true_return

    td, meta, cache = tiny_dataset
    root, cfg, keep, final, original = _fake_run_dir(td, cache, tmp_path)
    bench = load_script(root / "bench" / "tracked_replay.py", "bench_tracked_replay_mw")
    out = bench.tracked(tmp_path, horizon=150, tracker_steps=50, seed=0, progress=False)
    t = out["tracked"]
    assert t["true_return_mean_after"] == pytest.approx(t["true_return_mean_before"], rel=1e-9)
    assert t["true_return_max_after"] == t["true_return_max_before"]
    assert [s["start_row"] for s in out["samples"]] == [0, 2] and out["generated"]["num_generated"] == 2
    assert out["fidelity"]["recorded_mean"] == pytest.approx(float(true_return(td, horizon=150)[[1, 3, 0, 2]].mean()))
    assert out["fidelity"]["recorded_success_rate"] == float(td["next", "success"].any(-2).double().mean()) and out["fidelity"]["hand_deviation_median"] >= 0
    assert out["inpaint_start"] is False and out["top_k"] == 4
    # the twins are tracked as their originals: none is off path, so the on-path reading is the same
    assert out["generated"]["off_path"] == 0 and out["tracked_on_path"] == out["tracked"]
    # the recipe's analysis.tracked (off by default): tracked.json and the report rows
    import types

    recipe = load_script(root / "recipes" / "ftb_offline.py", "recipe_tracked_mw")
    run = types.SimpleNamespace(path=tmp_path)
    flow = {"trajectories": final, "original": original, "source_step": torch.tensor([1, 1, 0, 0]),
            "original_indices": torch.tensor([1, 3, 0, 2])}
    assert recipe.tracked_analysis(cfg, run, flow, td, meta, progress=False) is None  # off by default
    on = OmegaConf.merge(cfg, {"analysis": {"tracked": True}, "tracker": {"steps": 50}})
    ours = recipe.tracked_analysis(on, run, flow, td, meta, progress=False)
    assert ours["fidelity"] == out["fidelity"] and ours["tracked"] == out["tracked"] and "samples" not in ours
    # both default to the benchmarks' reading: shooting with 4 candidates, each generated path read 4 times
    assert ours["shooting"]["candidates"] == out["shooting"]["candidates"] == 4
    assert ours["shooting"]["readers"] == out["shooting"]["readers"] == 4
    assert len(json.loads((tmp_path / "tracked.json").read_text())["samples"]) == 2
    table = report_rows(recipe, analysis={"tracked": ours})
    assert table["true return top-k tracked in closed loop (stop rule, 150 steps; shooting, 4 candidates, generated "
                 "paths: mean of 4 readings): mean / max before -> after"]
    assert "generated in final set, tracked: return claimed -> tracked (hand off its path, m, median)" in table
    assert recipe.tracked_analysis(on, run, flow, td, {"domain": "toy"}, progress=False) is None
    with pytest.raises(ValueError, match="tracker.steps=0"):
        recipe.tracked_analysis(OmegaConf.merge(on, {"tracker": {"steps": 0}}), run, flow, td, meta,
                                progress=False)
    tracker = fit_path_tracker(td, steps=5, hidden=8)
    with pytest.raises(ValueError, match="not a generated Meta-World one"):
        tracked_improvement(final, original, torch.tensor([1, 1, 0, 0]) > 0, td, {"domain": "toy"},
                            task="button-press-v3", horizon=150, tracker=tracker)
    # a generated path 1 m above the table: the tracker cannot follow it, so it is off path and left out of the
    # on-path reading, whatever its tracked return
    flown = final.clone()
    flown["observation"][0, :, 2] += 1.0
    flown["observation"][0, :, 20] += 1.0
    off = tracked_improvement(flown, original, torch.tensor([1, 1, 0, 0]) > 0, td, meta, task="button-press-v3",
                              horizon=150, tracker=tracker, original_rows=torch.tensor([1, 3, 0, 2]))
    assert off["generated"]["off_path"] == 1
    assert off["samples"][0]["hand_deviation"] > off["fidelity"]["hand_deviation_max"] >= off["samples"][1]["hand_deviation"]
    on, all_ = off["tracked_on_path"], off["tracked"]
    assert on["true_return_mean_before"] == all_["true_return_mean_before"]
    assert 3 * on["true_return_mean_after"] == pytest.approx(4 * all_["true_return_mean_after"]
                                                             - off["samples"][0]["tracked_stop_rule"])
    with pytest.raises(ValueError, match="final-set originals"):  # an original the top-k does not hold
        tracked_improvement(keep[[0, 2]], keep[[1, 3]], torch.tensor([True, False]), td, meta,
                            task="button-press-v3", horizon=150, tracker=tracker, original_rows=torch.tensor([1, 3]))


@pytest.mark.integration
def test_shooting_tracker_reproduces_recorded_paths_and_corrects_wrong_actions(tiny_dataset, tmp_path, report_rows):
    """MetaWorldShootingController tries actions in the simulator from the state it reached: a recorded path's own
    actions land on it, so it is reproduced exactly; given wrong own actions and the right ones as its proposal it
    follows the path where the wrong actions open loop leave it. The analysis reading with candidates > 1
    (``tracker.candidates``) therefore tracks the recorded top-k to their recorded returns (fidelity 1)."""
    import numpy as np
    from omegaconf import OmegaConf

    from torchrl_ftb.analysis import track_paths, tracked_improvement
    from torchrl_ftb.analysis.replay import episode_jobs
    from torchrl_ftb.data.labels import true_return
    from torchrl_ftb.datasets.metaworld import generate_metaworld_episodes
    from torchrl_ftb.envs import MetaWorldShootingController
    from torchrl_ftb.policy import fit_path_tracker

    td, meta, cache = tiny_dataset
    seed, task = int(meta["seed"]), "button-press-v3"
    row = 2  # the random group's episode: 150 steps of contact-free wandering
    n = int(td["mask"][row].sum())
    path, acts = td["observation"][row].double().numpy(), td["action"][row].double().numpy()
    job = episode_jobs(meta, torch.tensor([row]))

    def run(controller):
        return generate_metaworld_episodes(task, job, seed=seed, noise=0.0, max_steps=150, controllers=[controller])[0]

    exact = run(MetaWorldShootingController(path, n, own_actions=acts, candidates=4, seed=0))
    np.testing.assert_allclose(exact["reward"], td["next", "reward"][row, :n, 0].numpy(), rtol=1e-5, atol=1e-5)
    # scored over 4 steps ahead: the own actions still land on every one of them, and each try starts from the
    # state the simulator reached (restored), so the path is still reproduced exactly
    ahead = run(MetaWorldShootingController(path, n, own_actions=acts, candidates=4, lookahead=4, seed=0))
    np.testing.assert_allclose(ahead["reward"], exact["reward"], rtol=1e-6, atol=1e-6)
    wrong = np.clip(acts + np.random.default_rng(0).normal(0.0, 0.8, acts.shape), -1.0, 1.0)
    steps = iter(acts)
    fixed = run(MetaWorldShootingController(path, n, own_actions=wrong, proposal=lambda obs: next(steps),
                                            candidates=2, tolerance=1e-5))
    open_loop = run(MetaWorldShootingController(path, n, own_actions=wrong, candidates=1))
    off = lambda ep: float(np.linalg.norm(ep["observation"][:n, :3] - path[:n, :3], axis=-1).max())  # noqa: E731
    assert off(fixed) < 1e-4 < 0.01 < off(open_loop)
    with pytest.raises(RuntimeError, match="attach"):
        MetaWorldShootingController(path, n, own_actions=acts)(path[0])
    with pytest.raises(ValueError, match="candidates >= 1"):
        MetaWorldShootingController(path, n, own_actions=acts, candidates=0)
    with pytest.raises(ValueError, match="one row per step"):
        MetaWorldShootingController(path, n, own_actions=acts[:5])
    with pytest.raises(ValueError, match="lookahead >= 1"):
        MetaWorldShootingController(path, n, own_actions=acts, lookahead=0)
    tracker = fit_path_tracker(td, steps=5, hidden=8)
    with pytest.raises(ValueError, match="needs the paths' own actions"):
        track_paths(task, job, td["observation"][[row]], [n], tracker, seed=seed, max_steps=150, candidates=3)

    # the analysis reading: the recorded top-k tracked exactly, whatever the (barely fitted) tracker proposes
    root, cfg, keep, final, original = _fake_run_dir(td, cache, tmp_path)
    rows = torch.tensor([1, 3, 0, 2])
    out = tracked_improvement(final, original, torch.tensor([1, 1, 0, 0]) > 0, td, meta, task=task, horizon=150,
                              tracker=tracker, original_rows=rows, candidates=3)
    recorded = true_return(td, horizon=150).double()[rows]
    assert out["fidelity"]["tracked_mean"] == pytest.approx(float(recorded.mean()), rel=1e-5)
    assert out["fidelity"]["tracked_max"] == pytest.approx(float(recorded.max()), rel=1e-5)
    assert out["fidelity"]["hand_deviation_max"] < 1e-4
    assert out["shooting"] == {"candidates": 3, "noise": 0.3, "lookahead": 1, "readers": 1}
    # readers: generated paths the simulator cannot follow (the hand shifted 5 cm from step 5) read again with other
    # perturbations; a path's numbers are its means over the readings, and reading 0 is the single reading
    shifted, generated = final.clone(), torch.tensor([1, 1, 0, 0]) > 0
    shifted["observation"][:2, 5:, 0:3] += 0.05
    kw = dict(task=task, horizon=150, tracker=tracker, original_rows=rows, candidates=3)
    one = tracked_improvement(shifted, original, generated, td, meta, **kw)
    many = tracked_improvement(shifted, original, generated, td, meta, readers=3, **kw)
    per = [s["tracked_stop_rule_per_reader"] for s in many["samples"]]
    assert [p[0] for p in per] == pytest.approx([s["tracked_stop_rule"] for s in one["samples"]])
    assert [s["tracked_stop_rule"] for s in many["samples"]] == pytest.approx([sum(p) / 3 for p in per])
    assert all(0.0 <= s["tracked_success"] <= 1.0 for s in many["samples"])
    assert many["tracked_per_reader"][0] == pytest.approx(one["tracked"]) and len(many["tracked_per_reader"]) == 3
    assert many["fidelity"] == one["fidelity"] and many["shooting"]["readers"] == 3
    assert any(len(set(p)) > 1 for p in per)  # other perturbations, another reading
    devs = [s["hand_deviation_per_reader"] for s in many["samples"]]
    assert [s["hand_deviation"] for s in many["samples"]] == pytest.approx([sum(d) / 3 for d in devs])
    # off path if any reading left it: at least the single reading's off-path samples
    limit = many["fidelity"]["tracker_alone_hand_deviation_max"]
    assert many["generated"]["off_path"] == sum(max(d) > limit for d in devs) >= one["generated"]["off_path"]
    with pytest.raises(ValueError, match="needs shooting"):
        tracked_improvement(shifted, original, generated, td, meta, task=task, horizon=150, tracker=tracker,
                            readers=2)
    with pytest.raises(ValueError, match="tracked_improvement: candidates=0: must be a whole number >= 1"):
        tracked_improvement(shifted, original, generated, td, meta, task=task, horizon=150, tracker=tracker,
                            candidates=0)
    # off path is judged against the tracker alone (shooting leaves real paths by nothing, generated ones by more)
    alone = tracked_improvement(final, original, torch.tensor([1, 1, 0, 0]) > 0, td, meta, task=task, horizon=150,
                                tracker=tracker, original_rows=rows)
    assert out["fidelity"]["tracker_alone_hand_deviation_max"] == pytest.approx(alone["fidelity"]["hand_deviation_max"])
    assert out["fidelity"]["tracker_alone_tracked_mean"] == pytest.approx(alone["fidelity"]["tracked_mean"])
    assert out["generated"]["off_path"] == 0 and out["tracked_on_path"] == out["tracked"]
    assert out["tracked"]["true_return_mean_after"] == pytest.approx(out["tracked"]["true_return_mean_before"])
    recipe = load_script(root / "recipes" / "ftb_offline.py", "recipe_shooting_mw")
    with pytest.raises(ValueError, match="tracker.candidates=0"):
        recipe.tracker_candidates(OmegaConf.merge(cfg, {"tracker": {"candidates": 0}}))
    with pytest.raises(ValueError, match="tracker.readers=2: more than one reading needs shooting"):
        recipe.tracker_readers(OmegaConf.merge(cfg, {"tracker": {"readers": 2, "candidates": 1}}))
    assert recipe.tracker_readers(OmegaConf.merge(cfg, {"tracker": {"readers": 2, "candidates": 4}})) == 2
    # unset (the config's null): four readings with shooting, one with the tracker alone, so candidates=1 alone is valid
    assert recipe.tracker_readers(OmegaConf.merge(cfg, {"tracker": {"readers": None, "candidates": 1}})) == 1
    assert recipe.tracker_candidates(cfg) == 4 and recipe.tracker_readers(cfg) == 4
    table = report_rows(recipe, analysis={"tracked": {**out, "shooting": {**out["shooting"], "lookahead": 5}}})
    assert ("true return top-k tracked in closed loop (stop rule, 150 steps; shooting, 3 candidates, 5-step "
            "lookahead): mean / max before -> after") in table
    table = report_rows(recipe, analysis={"tracked": many})
    assert ("true return top-k tracked in closed loop (stop rule, 150 steps; shooting, 3 candidates, generated "
            "paths: mean of 3 readings): mean / max before -> after") in table
