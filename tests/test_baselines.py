"""Tests of torchrl_ftb.baselines, recipes/baselines.py and bench/table1.py (fast, CPU)."""
from __future__ import annotations

import functools
import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs.transforms import ModuleTransform, RewardScaling

from torchrl_ftb.baselines import (
    METHODS,
    make_iql_model,
    make_offline_buffer,
    make_reward_transforms,
    reward_scale,
    run_baseline,
    select_top_trajectories,
    zero_reward_module,
)
from torchrl_ftb.data import pad_trajectories, trajectories_to_flat
from torchrl_ftb.data.labels import ReturnTeacher, make_scripted_labels
from torchrl_ftb.policy import evaluate_policy
from torchrl_ftb.testing import MetaWorldMockEnv, ToyLineEnv, load_script, make_toy_dataset

ROOT = Path(__file__).resolve().parents[1]
TINY = dict(
    network={"hidden": [16, 16]},
    bc={"steps": 3, "batch_size": 32},
    iql={"steps": 3, "batch_size": 32},
    td3bc={"steps": 3, "batch_size": 32},
    reward_model={"num_cells": 16},
    reward_training={"steps": 3},
    oprl_members=2,
    progress=False,
)

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def mock_data():
    """Meta-World-shaped data: random-action episodes of the mock env, with scripted labels."""
    env = MetaWorldMockEnv(max_steps=12)
    env.set_seed(0)
    torch.manual_seed(0)
    episodes = [env.rollout(12) for _ in range(10)]
    trajs = pad_trajectories(episodes)
    labels = make_scripted_labels(trajs, num_pairs=8, teacher=ReturnTeacher(), seed=0)
    return trajs, labels


# --------------------------------------------------------------------- data pieces
def test_reward_relabel_transform_applies_module_at_sample_time():
    trajs = make_toy_dataset(num_trajectories=8, horizon=8, seed=0)

    class Linear(torch.nn.Module):
        def forward(self, observation, action):
            return observation[..., :1] * 2.0 + action[..., :1]

    module = TensorDictModule(Linear(), in_keys=["observation", "action"], out_keys=[("next", "reward")])
    transforms = make_reward_transforms(trajs, reward_module=module, normalization="standardize")
    assert isinstance(transforms[0], ModuleTransform) and isinstance(transforms[1], RewardScaling)
    rb = make_offline_buffer(trajs, batch_size=64, seed=0, transforms=transforms)
    batch = rb.sample()
    expected_raw = batch["observation"][..., :1] * 2.0 + batch["action"][..., :1]
    # the relabelled reward is an affine map of the module's output, standardised over the dataset
    flat = trajectories_to_flat(trajs)
    all_raw = flat["observation"][..., :1] * 2.0 + flat["action"][..., :1]
    mean, std = all_raw.mean(), all_raw.std(unbiased=False)
    torch.testing.assert_close(batch["next", "reward"], (expected_raw - mean) / std, atol=1e-4, rtol=1e-4)
    assert not batch["next", "reward"].requires_grad
    # the stored data keeps its true reward
    stored = rb.storage.get(torch.arange(5))
    torch.testing.assert_close(stored["next", "reward"], flat[:5]["next", "reward"])


def test_zero_reward_and_true_reward_scaling():
    trajs = make_toy_dataset(num_trajectories=8, horizon=8, seed=1)
    rb = make_offline_buffer(trajs, batch_size=16, seed=0,
                             transforms=make_reward_transforms(trajs, reward_module=zero_reward_module(),
                                                               normalization="return_range"))
    assert float(rb.sample()["next", "reward"].abs().sum()) == 0.0  # constant reward: no division by 0
    loc, scale = reward_scale(trajs["next", "reward"], trajs["mask"], mode="return_range", target_range=1000.0)
    returns = (trajs["next", "reward"].squeeze(-1) * trajs["mask"]).sum(-1)
    assert loc == 0.0 and scale == pytest.approx(1000.0 / float(returns.max() - returns.min()), rel=1e-5)
    with pytest.raises(ValueError, match="normalization"):
        reward_scale(trajs["next", "reward"], trajs["mask"], mode="minmax")


def test_select_top_trajectories():
    trajs = make_toy_dataset(num_trajectories=20, horizon=4, seed=0)
    values = torch.randn(20)
    top, idx = select_top_trajectories(trajs, values, fraction=0.1)
    assert top.batch_size[0] == 2 and set(idx.tolist()) == set(values.topk(2).indices.tolist())
    torch.testing.assert_close(top["observation"], trajs["observation"][idx])
    with pytest.raises(ValueError, match="fraction"):
        select_top_trajectories(trajs, values, fraction=0.0)
    with pytest.raises(ValueError, match="values"):
        select_top_trajectories(trajs, values[:5])


# --------------------------------------------------------------------- methods: smoke
@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_runs_on_metaworld_shaped_data(method, mock_data):
    trajs, labels = mock_data
    result = run_baseline(method, trajs, labels=labels, seed=0, **TINY)
    assert result.method == method
    out = evaluate_policy(lambda: MetaWorldMockEnv(max_steps=5), result.actor, num_episodes=1, seed=0,
                          max_steps=5, stop_on_success=True)
    assert out["num_episodes"] == 1 and 0.0 <= out["success_rate"] <= 1.0
    actions = result.actor(TensorDict({"observation": trajs["observation"][0]}, [12]))["action"]
    assert actions.shape == (12, 4) and bool((actions.abs() <= 1).all()) and bool(torch.isfinite(actions).all())
    if method in ("iql_rpsi", "oprl", "bc10_score"):
        assert result.reward_model is not None and result.reward_model.num_members == (2 if method == "oprl" else 1)


def test_run_baseline_errors(mock_data):
    trajs, labels = mock_data
    with pytest.raises(ValueError, match="unknown baseline"):
        run_baseline("cql", trajs, **TINY)
    with pytest.raises(ValueError, match="labels"):
        run_baseline("iql_rpsi", trajs, labels=None, **TINY)
    with pytest.raises(ValueError, match="true reward"):
        run_baseline("iql", trajs.exclude(("next", "reward")), **TINY)
    with pytest.raises(ValueError, match="steps"):
        run_baseline("iql", trajs, iql={"batch_size": 8}, progress=False)


# --------------------------------------------------------------------- behaviour
def test_iql_with_true_reward_beats_bc_on_mixed_quality_toy_data():
    """Mixed-quality data (mean return ≈ 5 of an optimum of 32): BC imitates the average
    behaviour; IQL's advantage weighting must pick the good actions."""
    torch.manual_seed(0)
    horizon = 32
    trajs = make_toy_dataset(num_trajectories=128, horizon=horizon, seed=0)
    common = dict(seed=0, network={"hidden": [64, 64]}, progress=False)
    bc = run_baseline("bc", trajs, bc={"steps": 300, "batch_size": 256, "lr": 1e-3, "weight_decay": 0.0}, **common)
    iql = run_baseline("iql", trajs, iql={"steps": 250, "batch_size": 256, "lr": 1e-3},
                       reward_normalization="none", **common)

    def returns(actor):
        return evaluate_policy(lambda: ToyLineEnv(max_steps=horizon), actor, num_episodes=4, seed=123,
                               max_steps=horizon)["return_mean"]

    data_mean = float((trajs["next", "reward"].squeeze(-1) * trajs["mask"]).sum(-1).mean())
    r_bc, r_iql = returns(bc.actor), returns(iql.actor)
    assert r_iql > r_bc + 10.0, (r_iql, r_bc)
    assert r_iql > data_mean + 10.0 and r_iql > 0.6 * horizon, (r_iql, data_mean)


def test_iql_model_is_deterministic_in_eval_mode():
    model = make_iql_model(3, 2, hidden=(8,))
    td = TensorDict({"observation": torch.randn(6, 3)}, [6])
    evaluate = lambda: evaluate_policy(lambda: ToyLineEnv(max_steps=6), model[0], num_episodes=1,  # noqa: E731
                                       seed=0, max_steps=6)["return_mean"]
    assert evaluate() == evaluate()
    assert model[0](td.clone())["action"].shape == (6, 2)


# --------------------------------------------------------------------- recipe + harness
def test_recipe_runs_resumes_and_checkpoint_loads(tmp_path):
    from hydra import compose, initialize_config_dir

    recipe = load_script(ROOT / "recipes" / "baselines.py", "recipe_baselines")
    overrides = ["env.name=toy", "method=bc10_score", "dataset.num_trajectories=24", "dataset.horizon=8",
                 "labels.num_pairs=6", "bc.steps=5", "score_model.steps=3", "score_model.num_cells=8",
                 "bc.hidden=[8]", "eval.num_episodes=2", "progress=false", "logger.backend=csv",
                 "labels.query.strategy=disagreement", "labels.query.initial=3", "labels.query.per_round=2",
                 "labels.query.steps=2"]
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        cfg = compose(config_name="baselines", overrides=overrides + [f"run_dir={tmp_path}"])
        bad = compose(config_name="baselines", overrides=overrides + ["method=cql", f"run_dir={tmp_path / 'bad'}"])
        # BC's and the evaluation's numbers are refused before any data or training (bc.* only for BC methods)
        bad_numbers = {override: compose(config_name="baselines",
                                         overrides=overrides + [override, f"run_dir={tmp_path / 'numbers'}"])
                       for override in ("bc.lr=0", "bc.steps=2.5", "eval.num_episodes=0", "eval.max_steps=ten")}
        iql_bad_bc = compose(config_name="baselines", overrides=overrides + ["method=iql", "bc.lr=0", "iql.steps=0",
                                                                             f"run_dir={tmp_path / 'iql'}"])
    for override, message in (("bc.lr=0", r"bc.\*: train_bc: lr must be > 0"),
                              ("bc.steps=2.5", r"bc.\*: train_bc: steps must be a whole number, got 2.5"),
                              ("eval.num_episodes=0", r"eval.\*: evaluate_policy: num_episodes must be >= 1"),
                              ("eval.max_steps=ten", r"eval.\*: evaluate_policy: max_steps must be a number")):
        with pytest.raises(ValueError, match=message):
            recipe.run(bad_numbers[override])
    assert not (tmp_path / "numbers").exists()  # refused before anything is written
    recipe.check_config(iql_bad_bc)  # IQL does not read bc.*
    metrics = recipe.run(cfg)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["score"] == metrics["score"] and saved["uses_labels"] and saved["labels"]["num_pairs"] == 6
    assert saved["labels"]["query"] == "disagreement"
    assert saved["train"]["ranked_by"] == "learned score s_psi"
    ckpt = torch.load(tmp_path / "actor.pt", weights_only=True)
    assert ckpt["method"] == "bc10_score" and any(k.endswith("normalizer.loc") for k in ckpt["actor"])
    mtime = (tmp_path / "metrics.json").stat().st_mtime_ns
    assert recipe.run(cfg)["score"] == metrics["score"]  # resume: not redone
    assert (tmp_path / "metrics.json").stat().st_mtime_ns == mtime
    with pytest.raises(ValueError, match="unknown"):
        recipe.run(bad)


def test_table1_cell_command_names_the_ftb_config(tmp_path):
    table1 = load_script(ROOT / "bench" / "table1.py", "bench_table1")
    fake = tmp_path / "python"  # stands in for the interpreter: prints the command it got, fails
    fake.write_text("#!/bin/sh\necho \"$@\"\nexit 3\n")
    fake.chmod(0o755)
    out = table1.run_cell("ftb", "plate-slide-v3", 4, teacher="success", preset="cpu", extra=["eval.num_episodes=50"],
                          runs_dir=tmp_path / "runs", results_dir=tmp_path / "res", ftb_config="ftb_offline_metaworld",
                          python=str(fake))
    assert out is None  # a failed cell writes no JSON and keeps its log
    log = (tmp_path / "runs" / "failed" / "ftb__plate-slide-v3__success__seed4.log").read_text()
    assert "ftb_offline.py --config-name ftb_offline_metaworld env.name=plate-slide-v3 seed=4" in log
    assert log.splitlines()[0].endswith("progress=false eval.num_episodes=50") and not (tmp_path / "res").exists()


def test_table1_markdown_between_markers(tmp_path):
    table1 = load_script(ROOT / "bench" / "table1.py", "bench_table1")
    cells = tmp_path / "cells"
    for seed, score in ((0, 0.5), (1, 0.7)):
        table1.write_cell_json(cells / f"iql__button-press-v3__seed{seed}.json",
                               {"method": "iql", "env": "button-press-v3", "seed": seed, "score": score,
                                "score_name": "success_rate", "teacher": "return"})
    md = tmp_path / "BENCHMARKS.md"
    md.write_text("# Benchmarks\n\nintro\n\n<!-- table1:start -->\nold\n<!-- table1:end -->\n\ntail\n")
    table1.write_markdown(cells, md)
    text = md.read_text()
    assert text.startswith("# Benchmarks\n\nintro\n") and text.rstrip().endswith("tail") and "old" not in text
    section = text.split("<!-- table1:start -->")[1].split("<!-- table1:end -->")[0]
    assert "0.60 ± 0.10 (n=2)" in section and "paper" in section.lower() and "0.70" in section  # paper IQL 0.70
    # an FTB cell adds the flow table (what the flow did, not only the policy's score)
    table1.write_cell_json(cells / "ftb__button-press-v3__seed0.json", {
        "method": "ftb", "env": "button-press-v3", "seed": 0, "score": 1.0, "teacher": "success",
        "wall_time_s": 1200.0,
        "metrics": {"flow": {"flow_steps_run": 2, "num_generated_accepted": 37, "score_mean_before": 10.0,
                             "score_mean_after": 12.5, "true_return_mean_before": 100.0,
                             "true_return_mean_after": 140.0, "true_return_max_before": 300.0,
                             "true_return_max_after": 320.0},
                    "flow_stats": [{"valid_rate": 0.9, "accept_rate": 0.3}]}})
    table1.write_markdown(cells, md)
    section = md.read_text().split("<!-- table1:start -->")[1].split("<!-- table1:end -->")[0]
    assert "| button-press-v3 | success | 0 | 2 | 37 | 0.90 / 0.30 | 10.0 → 12.5 | 100.0 → 140.0 | 300.0 → 320.0 | 1.00 | 20.0 | — |" in section


def test_table1_compares_configurations_task_by_task(tmp_path):
    table1 = load_script(ROOT / "bench" / "table1.py", "bench_table1")
    dirs = {"a": tmp_path / "a", "b": tmp_path / "b"}
    for label, scores in (("a", (0.5, 0.7)), ("b", (1.0,))):
        for seed, score in enumerate(scores):
            for teacher in ("success", "return"):
                table1.write_cell_json(dirs[label] / f"ftb__plate-slide-v3__{teacher}__seed{seed}.json",
                                       {"method": "ftb", "env": "plate-slide-v3", "seed": seed, "teacher": teacher,
                                        "score": score if teacher == "success" else 0.0})
    table = table1.render_comparison(dirs, teacher="success")
    row = next(line for line in table.splitlines() if line.startswith("| plate-slide-v3"))
    # mean ± s.e. (population std 0.1 / sqrt 2), per-seed scores, the paper's FTB number
    assert row == "| plate-slide-v3 | 0.60 ± 0.07 (n=2; 0.50 / 0.70) | 1.00 ± 0.00 (n=1; 1.00) | 0.51±0.08 |"
    (dirs["b"] / "ftb__plate-slide-v3__success__seed0.json").rename(dirs["b"] / "ftb__plate-slide-v3__success__seed3.json")
    cell = json.loads((dirs["b"] / "ftb__plate-slide-v3__success__seed3.json").read_text())
    table1.write_cell_json(dirs["b"] / "ftb__plate-slide-v3__success__seed3.json", {**cell, "seed": 3})
    assert "(n=1; s3 1.00)" in table1.render_comparison(dirs, teacher="success")  # a lone seed is named
    with pytest.raises(SystemExit):  # a missing directory is refused by name
        table1.main(["--methods", "ftb", "--compare", f"x={tmp_path / 'missing'}"])


def test_table1_comparison_pools_episodes_into_a_wilson_interval(tmp_path):
    table1 = load_script(ROOT / "bench" / "table1.py", "bench_table1")
    cells = tmp_path / "c"
    for seed, (score, episodes) in enumerate(((0.0, 50), (0.05, 20), (0.0, 50))):
        table1.write_cell_json(cells / f"ftb__assembly-v3__success__seed{seed}.json", {
            "method": "ftb", "env": "assembly-v3", "seed": seed, "teacher": "success", "score": score,
            "score_name": "success_rate", "metrics": {"eval": {"num_episodes": episodes}}})
    k, n, low, high = table1.pooled_success(table1.load_cells(cells))
    assert (k, n) == (1, 120) and 0.0 < low < 1 / 120 < 0.02 < high < 0.05  # the paper's 0.02 is inside
    row = next(line for line in table1.render_comparison({"x": cells}, teacher="success").splitlines()
               if line.startswith("| assembly-v3"))
    assert row.startswith("| assembly-v3 | 0.02 ± 0.01 (n=3; 0.00 / 0.05 / 0.00; 1/120 ep., 95 % CI 0.00–0.05)")
    # a score that is not a whole number of successes is refused by cell, not pooled into nonsense
    bad = {"env": "assembly-v3", "seed": 0, "score_name": "success_rate", "score": 0.33,
           "metrics": {"eval": {"num_episodes": 20}}}
    with pytest.raises(ValueError, match="assembly-v3 seed 0.*not a whole number"):
        table1.pooled_success([bad])
    # without the episode count (or for a return) there is nothing to pool
    assert table1.pooled_success([{**bad, "metrics": {}}]) is None
    assert table1.pooled_success([{**bad, "score_name": "normalized_score"}]) is None


def test_table1_imports_a_finished_run_into_its_own_section(tmp_path):
    table1 = load_script(ROOT / "bench" / "table1.py", "bench_table1")
    run = tmp_path / "run"
    run.mkdir()
    metrics = {"env": "drawer-open-v3", "seed": 0, "teacher": "return", "preset": "cpu", "wall_time_s": 1560.0,
               "command": "recipes/ftb_offline.py env.name=drawer-open-v3", "eval": {"success_rate": 0.3}}
    (run / "metrics.json").write_text(json.dumps({k: v for k, v in metrics.items() if k != "teacher"}))
    cells = tmp_path / "cells_v2"
    with pytest.raises(ValueError, match="metrics.json.*lacks.*teacher"):
        table1.import_run(run, results_dir=cells)
    (run / "metrics.json").write_text(json.dumps(metrics))
    record = table1.import_run(run, results_dir=cells)
    assert (record["method"], record["score"], record["imported_from"]) == ("ftb", 0.3, str(run))
    assert (cells / "ftb__drawer-open-v3__return__seed0.json").exists()
    with pytest.raises(ValueError, match="exists"):  # never overwritten
        table1.import_run(run, results_dir=cells)
    # a locomotion run: the cell is named by env and dataset kind, as the harness names its cells
    loco = tmp_path / "loco"
    loco.mkdir()
    (loco / "metrics.json").write_text(json.dumps({**metrics, "env": "hopper", "eval": {"normalized_score": 6.4}}))
    (loco / "config.yaml").write_text("env:\n  name: hopper\ndataset:\n  options:\n    kind: medium-replay\n")
    assert table1.import_run(loco, results_dir=cells)["env"] == "hopper-medium-replay"
    assert (cells / "ftb__hopper-medium-replay__return__seed0.json").exists()
    assert table1.task_overrides("hopper-medium-replay")[1] == "+dataset.options.kind=medium-replay"
    md = tmp_path / "BENCHMARKS.md"
    md.write_text("# B\n\n<!-- table1:start -->\nkeep\n<!-- table1:end -->\n\n<!-- table1-v2:start -->\nold\n"
                  "<!-- table1-v2:end -->\n")
    table1.write_markdown(cells, md, section="table1-v2")
    text = md.read_text()
    assert "keep" in text and "old" not in text
    section = text.split("<!-- table1-v2:start -->")[1].split("<!-- table1-v2:end -->")[0]
    assert "0.30 ± 0.00 (n=1)" in section and "--section table1-v2" in section


def test_learned_reward_with_observation_normaliser():
    """``normalize_observations`` fits r_psi's normaliser on the dataset, and the relabelling
    transform then feeds raw observations through it (rewards unchanged by an obs offset)."""
    from torchrl_ftb.baselines import train_reward_model

    trajs = make_toy_dataset(num_trajectories=16, horizon=8, seed=0)
    labels = make_scripted_labels(trajs, num_pairs=8, teacher=ReturnTeacher(), seed=0)
    opts = dict(model={"num_cells": 16, "num_layers": 2, "normalize_observations": True},
                training={"steps": 5, "eval_fraction": 0.0}, progress=False)
    model, _ = train_reward_model(trajs, labels, **opts)
    assert model.normalizer_fitted
    shifted, shifted_labels = trajs.clone(), labels.clone()
    shifted["observation"] = trajs["observation"] + 100.0
    for k in ("tau0", "tau1"):
        shifted_labels[k, "observation"] = labels[k, "observation"] + 100.0
    model2, _ = train_reward_model(shifted, shifted_labels, **opts)
    r1 = make_reward_transforms(trajs, reward_module=model.reward_module)[0]
    r2 = make_reward_transforms(shifted, reward_module=model2.reward_module)[0]
    b1 = make_offline_buffer(trajs, batch_size=32, seed=0, transforms=[r1]).sample()
    b2 = make_offline_buffer(shifted, batch_size=32, seed=0, transforms=[r2]).sample()
    torch.testing.assert_close(b1["next", "reward"], b2["next", "reward"], atol=1e-3, rtol=1e-3)
    plain, _ = train_reward_model(trajs, labels, model={"num_cells": 16, "num_layers": 2},
                                  training={"steps": 5, "eval_fraction": 0.0}, progress=False)
    assert not plain.normalizer_fitted


def test_score_groups_report_splits_the_ranking_by_group():
    groups_bench = load_script(ROOT / "bench" / "score_groups.py", "bench_score_groups")
    returns = torch.tensor([1.0, 2.0, 3.0, 10.0, 20.0, 30.0], dtype=torch.float64)
    groups = torch.tensor([0, 0, 0, 1, 1, 1])
    lengths = torch.tensor([5.0, 5.0, 5.0, 9.0, 9.0, 9.0], dtype=torch.float64)
    # groups ordered right, the ranking inside group 1 reversed
    scores = torch.tensor([1.0, 2.0, 3.0, 30.0, 20.0, 10.0], dtype=torch.float64)
    rep = groups_bench.group_report(scores, returns, lengths, groups, ["a", "b"])
    assert rep["per_group"]["a"]["spearman_within"] == pytest.approx(1.0)
    assert rep["per_group"]["b"]["spearman_within"] == pytest.approx(-1.0)
    # overall 1 - 6 * 8 / 210; knowing only the group (ties inside groups) ranks better here
    assert rep["spearman"] == pytest.approx(1 - 48 / 210)
    assert rep["spearman_group_mean_return"] == pytest.approx(0.8783, abs=1e-4)
    assert rep["spearman_group_means"] != rep["spearman_group_means"]  # NaN: two groups are too few to rank
    assert rep["per_group"]["b"]["n"] == 3 and rep["per_group"]["b"]["return_mean"] == pytest.approx(20.0)


def test_score_model_variants_crop_and_parse():
    variants = load_script(ROOT / "bench" / "score_model_variants.py", "bench_score_model_variants")
    assert variants.parse_variant("crop50") == {"crop": 50}
    assert variants.parse_variant("pseudo0.99") == {"pseudo": 0.99}
    assert variants.parse_variant("wd1e-2") == {"weight_decay": 0.01}
    with pytest.raises(ValueError, match="unknown variant 'crop'"):
        variants.parse_variant("crop")
    valid = torch.tensor([3, 10, 7])  # prefix-valid masks of a [3, 12] batch
    mask = torch.arange(12) < valid[:, None]
    trajs = TensorDict({"mask": mask, "observation": torch.zeros(3, 12, 2)}, [3, 12])
    gen = torch.Generator().manual_seed(0)
    for _ in range(20):
        cropped = variants.crop_window(trajs, 5, gen)["mask"]
        assert not (cropped & ~mask).any()  # never a padded step
        assert cropped.sum(-1).tolist() == [3, 5, 5]  # shorter than the window: kept whole
        starts = cropped.float().argmax(-1)
        assert all(cropped[i, s:s + n].all() for i, (s, n) in enumerate(zip(starts.tolist(), [3, 5, 5])))
    assert trajs["mask"].equal(mask)  # the input is left alone


def test_bc_ceiling_selects_successes_or_whole_groups():
    bc_ceiling = load_script(ROOT / "bench" / "bc_ceiling.py", "bench_bc_ceiling")
    groups = ["expert", "within", "random", "cross"]
    group = torch.tensor([0, 0, 1, 1, 2, 3])
    success = torch.tensor([True, False, False, True, False, True])
    pick = functools.partial(bc_ceiling.select, group, success, groups, k=10)
    assert pick("on_task", generator=torch.Generator().manual_seed(0)).tolist() == [0, 3]
    assert pick("any", generator=torch.Generator().manual_seed(0)).tolist() == [0, 3, 5]
    assert pick("on_task", generator=torch.Generator().manual_seed(0), with_failures=True).tolist() == [0, 1, 2, 3]
    few = bc_ceiling.select(group, success, groups, "on_task", k=2, generator=torch.Generator().manual_seed(0),
                            with_failures=True)
    assert few.numel() == 2 and set(few.tolist()) <= {0, 1, 2, 3}


def test_table2_pairs_kinds_with_none_by_seed(tmp_path):
    table1 = load_script(ROOT / "bench" / "table1.py", "bench_table1")
    table2 = load_script(ROOT / "bench" / "table2.py", "bench_table2")
    task = "hopper-medium-replay"
    scores = {"none": {0: 5.0, 1: 6.0, 2: 7.0}, "ftb": {0: 6.0, 1: 8.0, 2: 10.0, 3: 99.0}}  # seed 3 has no pair
    for kind, per_seed in scores.items():
        for seed, score in per_seed.items():
            table1.write_cell_json(tmp_path / kind / f"td3bc__{task}__return__seed{seed}.json",
                                   {"method": "td3bc", "env": task, "seed": seed, "score": score})
    row = next(line for line in table2.paired(tmp_path).splitlines() if "| ftb − none |" in line)
    # differences +1, +2, +3: mean 2, s.e. 1/sqrt(3); only all-plus and all-minus reach |mean| 2 of 8 sign sets
    assert row == f"| {task} | td3bc | ftb − none | 0, 1, 2 | +1.00 / +2.00 / +3.00 | +2.00 ± 0.58 | 3/3 | 0.250 |"
    assert "synthetic" not in table2.paired(tmp_path)  # a kind with no cells gives no row
    table1.write_cell_json(tmp_path / "synthetic" / f"td3bc__{task}__return__seed2.json",
                           {"method": "td3bc", "env": task, "seed": 2, "score": 4.0})
    assert f"| {task} | td3bc | ftb − synthetic | 2 | +6.00 | +6.00 ± nan | 1/1 | 1.000 |" in table2.paired(tmp_path)
    assert table2.sign_flip_p([0.5, -0.5]) == 1.0 and table2.sign_flip_p([2.0] * 5) == 2 / 32
    with pytest.raises(ValueError, match="1 to 20"):
        table2.sign_flip_p([])
