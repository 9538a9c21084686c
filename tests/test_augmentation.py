"""FTB as data augmentation (torchrl_ftb.augmentation, recipes/baselines.py augmentation.kind)."""
from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModule

from torchrl_ftb.analysis import toy_oracle_step
from torchrl_ftb.augmentation import (
    TRANSITION_KEYS,
    as_transitions,
    build_supplement,
    ends_in_termination,
    flow_supplement,
    merge_datasets,
    synthetic_supplement,
)
from torchrl_ftb.baselines import make_offline_buffer
from torchrl_ftb.data.labels import true_return
from torchrl_ftb.diffusion import DiffusionSampler, make_diffuser
from torchrl_ftb.flow import FlowToBetter
from torchrl_ftb.testing import load_script, make_toy_dataset, toy_reward

ROOT = Path(__file__).resolve().parents[1]
GEN_KEYS = ("observation", "action", "mask", ("next", "reward"))

pytestmark = pytest.mark.usefixtures("one_thread")


def _generated(n=3, horizon=6):
    return make_toy_dataset(num_trajectories=n, horizon=horizon, seed=1).select(*GEN_KEYS)


def _double_reward_sampler():
    def better(cond):
        out = cond.select(*GEN_KEYS).clone()
        out["next", "reward"] = out["next", "reward"].abs() * 2 + 0.1
        return out

    return TensorDictModule(better, ["condition"], ["sample"])


def test_as_transitions_terminal_and_truncated_ends():
    gen = _generated()
    gen["mask"][1, 4:] = False  # ends early
    gen["mask"][2, 1:] = False  # a single step
    obs = gen["observation"].clone()
    term = as_transitions(gen, terminal_on_early_end=True)
    # full-length trajectory: last step has no successor -> dropped, previous step truncated
    assert term["mask"][0].sum() == 5 and bool(term["next", "truncated"][0, 4, 0])
    assert not bool(term["next", "terminated"][0].any())
    torch.testing.assert_close(term["next", "observation"][0, :5], obs[0, 1:6])
    # early end with terminal_on_early_end: kept and terminated
    assert term["mask"][1].sum() == 4 and bool(term["next", "terminated"][1, 3, 0]) and bool(term["next", "done"][1, 3, 0])
    assert term["mask"][2].sum() == 1 and bool(term["next", "terminated"][2, 0, 0])
    torch.testing.assert_close(term["next", "observation"][1, 3], obs[1, 3])  # terminal: stands in
    # Meta-World-like data (no termination): early ends are truncations, one-step trajectories vanish
    trunc = as_transitions(gen, terminal_on_early_end=False)
    assert trunc.batch_size[0] == 2 and not bool(trunc["next", "terminated"].any())
    assert trunc["mask"][1].sum() == 3 and bool(trunc["next", "truncated"][1, 2, 0])
    assert float(trunc["next", "reward"][~trunc["mask"]].abs().sum()) == 0.0
    # what an offline-RL update reads is all there
    rb = make_offline_buffer(trunc, batch_size=4, seed=0, require_reward=True)
    assert rb.sample()["next", "observation"].shape == (4, 3)


def test_ends_in_termination_and_merge():
    data = make_toy_dataset(num_trajectories=4, horizon=6, seed=0)
    assert ends_in_termination(data) == bool(data["next", "terminated"].any())
    sup = as_transitions(_generated(horizon=6), terminal_on_early_end=False)
    merged = merge_datasets(data, sup)
    assert merged.batch_size == (4 + sup.batch_size[0], 6)
    assert set(merged.keys(True, True)) == set(TRANSITION_KEYS)
    with pytest.raises(ValueError, match="horizons differ"):
        merge_datasets(data, as_transitions(_generated(horizon=5), terminal_on_early_end=False))
    with pytest.raises(ValueError, match="missing required key"):
        merge_datasets(data, _generated(horizon=6))  # not turned into transitions


def test_flow_keep_reward_carries_and_checks_the_reward():
    data = make_toy_dataset(num_trajectories=20, horizon=8, seed=0)
    supplement, result = flow_supplement(data, _double_reward_sampler(), top_k=5, flow_steps=2, progress=False)
    assert supplement.batch_size[0] == int((result.source_step > 0).sum()) > 0
    assert ("next", "reward") in supplement.keys(True)
    # the filter and the final ranking use the generated return
    torch.testing.assert_close(true_return(result.trajectories).double(), result.scores.double())
    no_reward = TensorDictModule(lambda c: c.select("observation", "action", "mask").clone(), ["condition"], ["sample"])
    with pytest.raises(ValueError, match="reward_channel=True"):
        flow_supplement(data, no_reward, top_k=5, flow_steps=1, progress=False)
    with pytest.raises(ValueError, match="missing required key"):
        FlowToBetter(_double_reward_sampler(), true_return, top_k=5, flow_steps=1, keep_reward=True,
                     progress=False)(data.exclude(("next", "reward")))


def test_synthetic_supplement_filters_invalid_samples():
    data = make_toy_dataset(num_trajectories=16, horizon=8, seed=0)
    diffuser = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=8, reward_channel=True, unconditional=True,
                             data=data)
    diffuser.update_ema()
    sampler = DiffusionSampler(diffuser, sampler="ddim", steps=3, seed=0)
    kept, info = synthetic_supplement(sampler, num_samples=5, normalizer=diffuser.normalizer, batch_size=2)
    assert info["generated"] == 5 and kept.batch_size[0] == info["valid"]
    assert ("next", "reward") in kept.keys(True) and bool((kept["action"].abs() <= 1).all())
    _, strict = synthetic_supplement(sampler, num_samples=4, normalizer=diffuser.normalizer, max_abs_z=1e-6)
    assert strict["valid"] == 0  # an untrained model's samples are not within 1e-6 z of the mean


@pytest.fixture(scope="module")
def supplements(tmp_path_factory):
    """FTB and SYNTHETIC supplements of the toy task (tiny diffuser, 250 steps each)."""
    cache = tmp_path_factory.mktemp("aug")
    data = make_toy_dataset(num_trajectories=256, horizon=8, seed=0, noise=0.0)
    common = dict(cache_dir=cache, diffuser={"preset": "tiny", "steps": 250, "lr": 3e-3, "sample_steps": 50},
                  flow={"top_k": 32, "flow_steps": 3, "threshold": 1.05, "batch_size": 64}, num_blocks=4,
                  seed=0, true_reward_fn=toy_reward, oracle_step=partial(toy_oracle_step, horizon=8), progress=False)
    out = {kind: build_supplement(kind, data, **common) for kind in ("ftb", "synthetic")}
    return data, common, out


def test_ftb_supplement_is_better_than_synthetic_in_true_return(supplements):
    """The paper's point (§4.4): FTB adds *better* trajectories, SYNTHETIC more of the same."""
    data, _, out = supplements
    top = true_return(data).sort(descending=True).values[:32]
    (ftb, ftb_info), (syn, syn_info) = out["ftb"], out["synthetic"]
    print({k: ftb_info[k] for k in ("true_return_mean", "generated_return_mean")}, syn_info["true_return_mean"])
    assert ftb.batch_size[0] > 0 and syn.batch_size[0] > 0
    # about as good as the top-k it started from (dataset mean: 0.6), far better than SYNTHETIC's
    assert ftb_info["true_return_mean"] > 0.9 * float(top.mean())
    assert ftb_info["true_return_mean"] > syn_info["true_return_mean"] + 3.0
    assert ftb_info["dynamics_error_mean"] > 0 and syn_info["dynamics_error_mean"] > 0  # reported, not exact
    assert set(ftb.keys(True, True)) == set(TRANSITION_KEYS)


def test_build_supplement_is_cached_and_checked(supplements):
    data, common, out = supplements
    again, info = build_supplement("ftb", data, **common)
    assert info["loaded"] and info["path"] == out["ftb"][1]["path"]
    assert torch.equal(again["observation"], out["ftb"][0]["observation"])
    assert "replayed_return_mean" not in info
    # simulator readings (here stand-ins computed from the stored reward) are read for a cached supplement too
    seen = []
    _, replayed = build_supplement("ftb", data, **common, readings={
        "replayed": lambda t: seen.append(t) or 2 * true_return(t), "tracked": lambda t: true_return(t) - 1})
    assert replayed["loaded"] and len(seen) == 1 and seen[0].batch_size == again.batch_size
    assert replayed["replayed_return_mean"] == pytest.approx(2 * float(true_return(again).mean()), rel=1e-6)
    assert replayed["replayed_return_max"] == pytest.approx(2 * float(true_return(again).max()), rel=1e-6)
    assert replayed["tracked_return_mean"] == pytest.approx(float(true_return(again).mean()) - 1, rel=1e-6)
    # a different setting never reuses the supplement: it lands in another directory
    changed = {**common, "flow": {**common["flow"], "threshold": 1.2}, "diffuser": {**common["diffuser"], "steps": 1}}
    assert build_supplement("ftb", data, **changed)[1]["path"] != info["path"]
    # SYNTHETIC's validity limits and the dataset's termination flags are part of the key too
    quick = {**common, "diffuser": {**common["diffuser"], "steps": 1, "sample_steps": 2}}
    strict = {**quick, "flow": {**quick["flow"], "max_abs_z": 3.0}}
    assert build_supplement("synthetic", data, **quick)[1]["path"] != build_supplement("synthetic", data, **strict)[1]["path"]
    from torchrl_ftb.augmentation.augment import _fingerprint

    falls = data.clone()
    falls["next", "terminated"][0, -1] = True
    assert _fingerprint(falls) != _fingerprint(data)
    # a score-conditioned diffuser gets each condition's normalised true return from the block pairs
    scored = {**common, "diffuser": {**common["diffuser"], "steps": 2, "overrides": {"score_condition": True}}}
    assert build_supplement("ftb", data, **scored)[1]["diffuser"]["step"] == 2
    Path(info["path"], "supplement.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="supplement"):
        build_supplement("ftb", data, **common)
    with pytest.raises(ValueError, match="kind must be"):
        build_supplement("none", data, **common)
    with pytest.raises(ValueError, match=r"unknown flow option\(s\) \['topk'\]"):
        build_supplement("ftb", data, **{**common, "flow": {"topk": 3}})
    with pytest.raises(ValueError, match="unknown diffuser option"):
        build_supplement("ftb", data, **{**common, "diffuser": {"preset": "tiny", "step": 3}})


def test_baselines_recipe_with_augmentation(tmp_path):
    from hydra import compose, initialize_config_dir

    recipe = load_script(ROOT / "recipes" / "baselines.py", "recipe_baselines_aug")
    overrides = ["env.name=toy", "method=iql", "dataset.num_trajectories=24", "dataset.horizon=8", "iql.steps=5",
                 "network.hidden=[8]", "eval.num_episodes=2", "progress=false", "logger.backend=csv",
                 "augmentation.diffuser.preset=tiny", "augmentation.diffuser.steps=5",
                 "augmentation.diffuser.sample_steps=3", "augmentation.flow.top_k=6"]
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "config"), version_base="1.3"):
        cfgs = {kind: compose(config_name="baselines", overrides=overrides + [
            f"augmentation.kind={kind}", f"run_dir={tmp_path / kind}", f"augmentation.cache_dir={tmp_path / 'cache'}"])
            for kind in ("synthetic", "ftb")}
        mismatch = compose(config_name="baselines", overrides=overrides + [f"run_dir={tmp_path / 'ftb'}"])
        bad = compose(config_name="baselines", overrides=overrides + ["method=iql_rpsi", "augmentation.kind=ftb",
                                                                      f"run_dir={tmp_path / 'bad'}"])
    for kind, cfg in cfgs.items():
        metrics = recipe.run(cfg)
        saved = json.loads((tmp_path / kind / "metrics.json").read_text())
        assert saved["augmentation"]["kind"] == kind and saved["score"] == metrics["score"]
        assert saved["augmentation"]["path"].startswith(str(tmp_path / "cache"))
        assert "Data augmented with" in (tmp_path / kind / "report.md").read_text()
    with pytest.raises(ValueError, match="augmentation.kind='none'"):
        recipe.run(mismatch)  # resume into a finished run of another augmentation
    with pytest.raises(ValueError, match="only"):
        recipe.run(bad)
    with pytest.raises(ValueError, match="augmentation.tracked=true with env.name='toy'"):
        recipe.run(OmegaConf.merge(cfgs["ftb"], {"augmentation": {"tracked": True}}))


def test_supplement_readings_track_a_locomotion_supplement():
    """``augmentation.tracked``: the recipe's closed-loop reading of a locomotion supplement. Recorded paths (which
    the simulator can follow) are tracked to their recorded return, on the scale of the data's top-k."""
    from torchrl_ftb.envs import make_locomotion_env

    recipe = load_script(ROOT / "recipes" / "baselines.py", "recipe_baselines_readings")
    env = make_locomotion_env("hopper", seed=0)
    trajs = torch.stack([env.rollout(6) for _ in range(3)]).select("observation", "action", ("next", "reward"))
    trajs["mask"] = torch.ones(3, 6, dtype=torch.bool)
    cfg = OmegaConf.create({"env": {"name": "hopper"}, "augmentation": {"tracked": False, "flow": {"top_k": 2}}})
    assert set(recipe.supplement_readings(cfg, trajs)) == {"replayed"}
    cfg.augmentation.tracked = True
    readings = recipe.supplement_readings(cfg, trajs)
    recorded = true_return(trajs).double()
    for name in ("replayed", "tracked"):
        assert torch.allclose(readings[name](trajs), recorded, atol=1e-3), name
