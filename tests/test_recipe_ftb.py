"""Tests of recipes/ftb_offline.py: tiny toy run end to end, kill-and-resume, clear errors."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_ftb.data.labels import SuccessTeacher
from torchrl_ftb.datasets import dataset_kwargs, make_dataset
from torchrl_ftb.envs import fit_metaworld_contact_reach, metaworld_contactless_object_path
from torchrl_ftb.testing import load_script

ROOT = Path(__file__).resolve().parents[1]
CONFIG_DIR = ROOT / "recipes" / "config"
TINY = [
    "env.name=toy", "dataset.horizon=16", "dataset.num_trajectories=48", "labels.num_pairs=30",
    "score_model.steps=40", "score_model.num_cells=32", "diffuser.preset=tiny", "diffuser.steps=40",
    "diffuser.overrides={hidden_dim:16,cond_dim:16}",
    "diffuser.checkpoint_every=2", "diffuser.sampler=ddim", "diffuser.sample_steps=4", "flow.top_k=8",
    "flow.max_flow_steps=2", "bc.steps=40", "bc.batch_size=128", "bc.hidden=[32,32]", "bc.checkpoint_every=10",
    "eval.num_episodes=2", "analysis.validity_reference_steps=20", "progress=false", "logger.backend=csv",
]

pytestmark = [pytest.mark.filterwarnings("ignore::UserWarning"), pytest.mark.usefixtures("one_thread")]


def _recipe():
    return load_script(ROOT / "recipes" / "ftb_offline.py", "ftb_offline_recipe")


def _cfg(run_dir: Path, *extra: str):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose(config_name="ftb_offline", overrides=[*TINY, f"run_dir={run_dir}", *extra])


def test_kill_during_diffuser_training_then_resume_end_to_end(tmp_path):
    run_dir = tmp_path / "run"
    ckpt = run_dir / "checkpoints" / "diffuser" / "diffuser_last.pt"
    cmd = [sys.executable, str(ROOT / "recipes" / "ftb_offline.py"), *TINY, f"run_dir={run_dir}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 90
        while not ckpt.exists():
            if proc.poll() is not None:
                pytest.fail(f"recipe exited early ({proc.returncode}): {proc.stderr.read().decode()[-2000:]}")
            if time.time() > deadline:
                pytest.fail("no diffuser checkpoint within 90 s")
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    stages = json.loads((run_dir / "stages.json").read_text())
    assert stages["score_model"]["done"] and stages["blocks"]["done"] and "diffuser" not in stages
    killed_at = int(torch.load(ckpt, weights_only=True)["step"])
    assert 0 < killed_at < 40

    recipe = _recipe()
    # a fresh run into the same directory is refused (nothing overwritten)
    with pytest.raises(ValueError, match="resume=true"):
        recipe.run(_cfg(run_dir))
    # resuming with a different config is refused too
    with pytest.raises(ValueError, match="different config"):
        recipe.run(_cfg(run_dir, "resume=true", "flow.threshold=1.5"))
    metrics = recipe.run(_cfg(run_dir, "resume=true"))
    assert metrics["diffuser"]["resumed_from"] >= killed_at and metrics["diffuser"]["steps"] == 40
    assert metrics["bc"]["steps"] == 40 and metrics["eval"]["num_episodes"] == 2
    for name in ("metrics.json", "report.md", "config.yaml", "plots/flow_steps.png",
                 "plots/scores_before_after.png", "plots/true_return_before_after.png"):
        assert (run_dir / name).is_file(), name
    assert "success rate" in (run_dir / "report.md").read_text()
    # the score model learnt the toy preference; the final set is at least as good as the start
    assert metrics["score_quality"]["spearman_return"] > 0.5
    quality = metrics["score_quality"]
    assert quality["top_k_success"] >= quality["dataset_success"]  # s_psi's top-k holds more successes
    assert "successes in the top-k" in (run_dir / "report.md").read_text()
    # bench/topk_success.py reads the same share back from the run's saved scores
    bench = load_script(ROOT / "bench" / "topk_success.py", "bench_topk_success")
    rep = bench.cell_report({"metrics": metrics, "run_dir": str(run_dir)}, run_dir, {})
    assert rep["top_k_success"] == pytest.approx(quality["top_k_success"]) and rep["top_k"] == 8
    assert metrics["flow"]["score_mean_after"] >= metrics["flow"]["score_mean_before"]

    # a second resume loads every finished stage and retrains nothing
    again = recipe.run(_cfg(run_dir, "resume=true"))
    assert again["eval"] == metrics["eval"]

    # redo_from: the flow (with a changed flow setting) and later stages are redone, the
    # diffuser and earlier stages are loaded, not retrained
    diffuser_mtime = ckpt.stat().st_mtime_ns
    redone = recipe.run(_cfg(run_dir, "resume=true", "redo_from=flow", "flow.threshold=1.01",
                             "diffuser.guidance=2.0", "flow.true_return_horizon=32"))  # flow-stage settings
    assert ckpt.stat().st_mtime_ns == diffuser_mtime
    assert redone["flow"]["threshold"] == 1.01 and metrics["flow"]["threshold"] != 1.01
    # the filled true return (stop-rule fill to 32 steps) beside the plain one, and bench/flow_generated.py
    # recomputes both from the saved flow checkpoint
    assert redone["flow"]["true_return_mean_before"] == pytest.approx(metrics["flow"]["true_return_mean_before"])
    assert "true_return_filled_mean_before" in redone["flow"] and "true_return_filled_mean_before" not in metrics["flow"]
    assert metrics["analysis"]["improvement"]["true_return_mean_after"] == metrics["flow"]["true_return_mean_after"]
    assert redone["analysis"]["improvement"]["true_return_filled_mean_after"] == redone["flow"]["true_return_filled_mean_after"]
    assert (run_dir / "plots" / "true_return_filled_before_after.png").is_file()
    gen = load_script(ROOT / "bench" / "flow_generated.py", "bench_flow_generated")
    entry = gen.measure_run(run_dir, horizon=32, max_frame_stack_error=0.02, max_hand_model_error=0.01,
                            contact_quantile=0.99)
    rows, imp = entry["generated_in_final_set"], entry["improvement"]
    flow_ckpt = torch.load(run_dir / "checkpoints" / "flow.pt", weights_only=True)
    assert len(rows) == int((flow_ckpt["source_step"] > 0).sum()) and entry["physically_invalid_in_final_set"] == 0
    assert all(r["frame_stack_error_m"] is None for r in rows)  # no Meta-World checks on the toy
    assert imp["filled_32_physically_checked"] == imp["filled_32"]
    assert gen.describe_run(run_dir, entry).startswith("  plain: mean ")
    table = gen.summary_table({"cells": {
        "config": {"max_frame_stack_error": 0.02, "max_hand_model_error": 0.01},
        "runs": {"r": entry}}}).splitlines()
    assert len(table) == 3 and table[2].startswith("| cells | toy | 0 | raw |") and "(any: 0)" in table[2]
    physics = load_script(ROOT / "bench" / "sample_physics.py", "bench_sample_physics")
    with pytest.raises(ValueError, match="needs a Meta-World run"):  # clear refusal, before any sampling
        physics.sample_physics(run_dir, conditions=2, top_k=None, seed=0)
    for ours, recipe_key in (("plain", "true_return"), ("filled_32", "true_return_filled")):
        for stat in ("mean_before", "mean_after", "max_after"):
            assert imp[ours][f"true_return_{stat}"] == pytest.approx(redone["flow"][f"{recipe_key}_{stat}"], abs=1e-4)
    assert json.loads((run_dir / "stages.json").read_text())["eval"]["done"]
    with pytest.raises(ValueError, match="different config"):  # earlier stages' settings still locked
        recipe.run(_cfg(run_dir, "resume=true", "redo_from=flow", "diffuser.batch_size=7"))
    assert json.loads((run_dir / "stages.json").read_text())["flow"]["done"]  # refused: nothing removed
    assert (run_dir / "checkpoints" / "flow.pt").is_file()
    with pytest.raises(ValueError, match="guidance"):  # ... and the flow's, unless the flow is redone
        recipe.run(_cfg(run_dir, "resume=true", "redo_from=bc", "flow.threshold=1.01"))
    with pytest.raises(ValueError, match="not a stage"):
        recipe.run(_cfg(run_dir, "resume=true", "redo_from=sampling"))
    # bc.seed: BC again on the same flowed set with another seed (the flow is loaded, not redone)
    flow_mtime = (run_dir / "checkpoints" / "flow.pt").stat().st_mtime_ns
    reseeded = recipe.run(_cfg(run_dir, "resume=true", "redo_from=bc", "flow.threshold=1.01", "diffuser.guidance=2.0",
                               "flow.true_return_horizon=32", "bc.seed=7"))
    assert (run_dir / "checkpoints" / "flow.pt").stat().st_mtime_ns == flow_mtime
    assert reseeded["flow"] == redone["flow"] and redone["bc"]["seed"] == 0 and reseeded["bc"]["seed"] == 7
    assert reseeded["bc"]["final_loss"] != redone["bc"]["final_loss"]
    with pytest.raises(ValueError, match="bc.seed=-1: must be a whole number >= 0, or null"):
        recipe.run(_cfg(tmp_path / "bad_seed", "bc.seed=-1"))
    assert not (tmp_path / "bad_seed").exists()

    # accepted samples on an env with a one-step oracle (toy): their dynamics error beside the data's and an MLP
    # model's on held-out real transitions, by step in plots/validity_per_step.png
    accepting = recipe.run(_cfg(run_dir, "resume=true", "redo_from=flow", "flow.threshold=1.0", "flow.top_k=40"))
    assert accepting["flow"]["fraction_generated_in_final"] > 0
    v = accepting["analysis"]["validity"]
    assert v["dynamics_error_dataset"] < 1e-5 < v["dynamics_error_mlp_heldout"] < v["dynamics_error_generated"]
    assert (run_dir / "plots" / "validity_per_step.png").is_file()

    # the oracle filter (flow.filter=true_return): the top-k, the acceptance and the final ranking
    # by the true return (here the 32-step fill), an upper bound labelled as such, not PbRL
    flow_kw = ("flow.threshold=1.01", "diffuser.guidance=2.0", "flow.true_return_horizon=32")
    oracle = recipe.run(_cfg(run_dir, "resume=true", "redo_from=flow", *flow_kw, "flow.filter=true_return"))
    assert oracle["flow_filter"] == "true_return" and redone["flow_filter"] == "score_model"
    fo, fs = oracle["flow"], redone["flow"]
    assert fo["score_mean_before"] == pytest.approx(fo["true_return_filled_mean_before"])  # one definition
    assert fo["score_mean_after"] == pytest.approx(fo["true_return_filled_mean_after"])
    # the true top-k holds at least the true return of s_psi's top-k, and the final set never loses it
    assert fo["true_return_filled_mean_before"] >= fs["true_return_filled_mean_before"] - 1e-6
    assert fo["true_return_filled_max_before"] >= fs["true_return_filled_max_before"] - 1e-6
    assert fo["true_return_filled_mean_after"] >= fo["true_return_filled_mean_before"] - 1e-6
    assert "true return (oracle bound" in (run_dir / "report.md").read_text()
    assert "read off their generated states" in (run_dir / "report.md").read_text()
    # the successes row counts the set the flow started from: the oracle's top-k here, s_psi's otherwise
    flow_ckpt = torch.load(run_dir / "checkpoints" / "flow.pt", weights_only=True)
    data, _ = make_dataset("toy", **dataset_kwargs("toy", _cfg(run_dir).dataset, max_episode_steps=32, progress=False))
    ok = SuccessTeacher().succeeded(data).float()
    assert fo["top_k_success"] == pytest.approx(float(ok[flow_ckpt["original_indices"]].mean()))
    assert fs["top_k_success"] == pytest.approx(redone["score_quality"]["top_k_success"])
    assert "successes in the filter's top-k / s_psi's" in (run_dir / "report.md").read_text()
    with pytest.raises(ValueError, match="flow.filter='best': choose one of"):
        recipe.run(_cfg(run_dir, "resume=true", "redo_from=flow", *flow_kw, "flow.filter=best"))
    with pytest.raises(ValueError, match="flow.filter=true_return .* needs flow.true_reward=true"):
        recipe.run(_cfg(tmp_path / "oracle", "flow.filter=true_return", "flow.true_reward=false"))
    assert not (tmp_path / "oracle").exists()

    # score guidance by its own 2-member ensemble, pessimistic: trained once beside s_psi, reused when only the
    # flow's settings change (redo_from=flow), removed with s_psi (redo_from=score_model, below)
    guide_kw = ("diffuser.score_guidance=0.3", "diffuser.score_guidance_members=2")
    guided = recipe.run(_cfg(run_dir, "resume=true", "redo_from=flow", *flow_kw, *guide_kw,
                             "diffuser.score_guidance_kappa=1"))
    guide_ckpt = run_dir / "checkpoints" / "guide_score_model.pt"
    assert guided["guide"]["trained"] and guided["guide"]["kappa"] == 1.0 and "guide" in guided["stage_time_s"]
    written = guide_ckpt.stat().st_mtime_ns
    reused = recipe.run(_cfg(run_dir, "resume=true", "redo_from=flow", *flow_kw, *guide_kw,
                             "diffuser.score_guidance_kappa=0.5"))
    assert not reused["guide"]["trained"] and guide_ckpt.stat().st_mtime_ns == written
    assert "guide" not in recipe.run(_cfg(run_dir, "resume=true", "redo_from=bc", *flow_kw, *guide_kw,
                                          "diffuser.score_guidance_kappa=0.5"))  # the flow is loaded: no guide

    # the score model's observation normaliser: on by default (fitted buffers saved), off
    # when asked (redo_from=score_model lets that section change)
    score_ckpt = run_dir / "checkpoints" / "score_model.pt"
    state = torch.load(score_ckpt, weights_only=True)["state_dict"]
    scale_key = next(k for k in state if k.endswith("obs_scale"))
    assert not bool((state[scale_key] == 1).all())
    # ... and a 2-member ensemble with the pessimistic flow filter (every member must agree)
    ens = ("score_model.num_members=2", "flow.ensemble_rule=all")
    out = recipe.run(_cfg(run_dir, "resume=true", "redo_from=score_model", "score_model.normalize_observations=false",
                          "flow.threshold=1.01", *ens))
    saved = torch.load(score_ckpt, weights_only=True)
    assert bool((saved["state_dict"][scale_key] == 1).all())
    assert saved["hparams"]["num_members"] == 2 and out["flow"]["filter_members"] == 2
    assert not guide_ckpt.exists()  # the guide's ensemble went with s_psi

    # a corrupt checkpoint is a clear error and is left as it was
    score_ckpt.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="corrupt"):
        recipe.run(_cfg(run_dir, "resume=true", "flow.threshold=1.01",
                        "score_model.normalize_observations=false", *ens))
    assert score_ckpt.read_bytes() == b"garbage"


def test_bad_config_is_a_clear_error(tmp_path):
    recipe = _recipe()
    with pytest.raises(ValueError, match="unknown env 'no-such-task-v3'.*Meta-World"):
        recipe.run(_cfg(tmp_path / "a", "env.name=no-such-task-v3"))
    with pytest.raises(ValueError, match="preset='gpu' is unknown"):
        recipe.run(_cfg(tmp_path / "b", "preset=gpu"))
    with pytest.raises(ValueError, match="teacher"):
        recipe.run(_cfg(tmp_path / "c", "labels.teacher=oracle"))
    # the toy env's observation has no stacked frames to rebuild
    with pytest.raises(ValueError, match="no known observation structure for env 'toy'"):
        recipe.run(_cfg(tmp_path / "e", "diffuser.observation_structure=true"))
    with pytest.raises(ValueError, match="max_frame_stack_error is a Meta-World check"):
        recipe.run(_cfg(tmp_path / "f", "flow.max_frame_stack_error=0.02"))
    with pytest.raises(ValueError, match="max_hand_model_error is a Meta-World check"):
        recipe.run(_cfg(tmp_path / "f", "flow.max_hand_model_error=0.01"))
    with pytest.raises(ValueError, match="max_contactless_object_path is a Meta-World check"):
        recipe.run(_cfg(tmp_path / "f", "flow.max_contactless_object_path=0.1"))
    with pytest.raises(ValueError, match="max_hand_step is a Meta-World check"):
        recipe.run(_cfg(tmp_path / "f", "flow.max_hand_step=1x"))
    with pytest.raises(ValueError, match="flow.max_hand_model_error='tight'"):
        recipe.run(_cfg(tmp_path / "f", "flow.max_hand_model_error=tight"))
    with pytest.raises(ValueError, match="tracker.steps=0: must be >= 1"):  # before any training, not at BC
        recipe.run(_cfg(tmp_path / "f", "tracker.steps=0"))
    # the flow's, BC's and the evaluation's numbers: refused before any training, not at their stages
    for override, message in (("flow.top_k=0", r"flow.\* \(or blocks.num_blocks\): FlowToBetter: top_k must be >= 1"),
                              ("flow.threshold=0.9", "threshold σ must be >= 1"),
                              ("flow.early_stop_fraction=1.5", r"early_stop_fraction must be in \[0, 1\]"),
                              ("flow.candidates=0", "candidates must be >= 1"),
                              ("flow.top_k=null", r"flow.\* \(or blocks.num_blocks\): int\(\) argument"),
                              ("flow.true_return_horizon=0", "flow.true_return_horizon=0: must be a whole number >= 1"),
                              ("flow.true_return_streak=ten", "flow.true_return_streak='ten': must be a whole number"),
                              ("flow.ensemble_rule=all", "needs a ScoreModel ensemble"),
                              ("bc.batch_size=0", r"bc.\*: train_bc: batch_size must be >= 1, got 0"),
                              ("bc.lr=0", "train_bc: lr must be > 0"),
                              ("bc.steps=many", r"bc.\*: train_bc: steps must be a number, got 'many'"),
                              ("eval.num_episodes=0", r"eval.\*: evaluate_policy: num_episodes must be >= 1"),
                              ("eval.max_steps=0", r"eval.\*: evaluate_policy: max_steps must be >= 1"),
                              ("diffuser.pair_neighbours=0", "diffuser.pair_neighbours=0: must be null or an integer"),
                              ("diffuser.top_block_pairs=1", "diffuser.top_block_pairs=1: must be true or false")):
        with pytest.raises(ValueError, match=message):
            recipe.run(_cfg(tmp_path / "f", override))
    assert not (tmp_path / "f").exists()  # refused before anything is written
    with pytest.raises(ValueError, match="flow.top_k=1000 exceeds the dataset's"):  # once the dataset is loaded
        recipe.run(_cfg(tmp_path / "k", "flow.top_k=1000"))
    assert not (tmp_path / "k" / "checkpoints" / "labels").exists()
    with pytest.raises(ValueError, match="score_model.horizon is the stop-rule fill"):
        recipe.run(_cfg(tmp_path / "h", "env.name=hopper", "score_model.horizon=1000"))
    with pytest.raises(ValueError, match="flow.true_return_horizon is the stop-rule fill"):
        recipe.run(_cfg(tmp_path / "h2", "env.name=hopper", "flow.true_return_horizon=1000"))
    assert not (tmp_path / "h").exists()
    with pytest.raises(ValueError, match="flow.true_return_streak is the Meta-World stop rule's cut"):
        recipe.run(_cfg(tmp_path / "h3", "flow.true_return_horizon=64", "flow.true_return_streak=25"))
    with pytest.raises(ValueError, match="flow.true_return_streak needs flow.true_return_horizon"):
        recipe.run(_cfg(tmp_path / "h3", "env.name=button-press-v3", "flow.true_return_streak=25"))
    assert not (tmp_path / "h3").exists()
    with pytest.raises(ValueError, match=r"diffuser.strength=0: must be a number in \(0, 1\]"):
        recipe.run(_cfg(tmp_path / "s", "diffuser.strength=0"))
    with pytest.raises(ValueError, match="diffuser.strength=1.5"):
        recipe.run(_cfg(tmp_path / "s", "diffuser.strength=1.5"))
    with pytest.raises(ValueError, match="diffuser.score_guidance=-0.1"):
        recipe.run(_cfg(tmp_path / "s", "diffuser.score_guidance=-0.1"))
    assert not (tmp_path / "s").exists()
    with pytest.raises(ValueError, match=r"labels.query.strategy='margin': choose one of \['random'"):
        recipe.run(_cfg(tmp_path / "g", "labels.query.strategy=margin"))
    assert not (tmp_path / "g").exists()
    # a dataset whose dims do not match the env
    from torchrl_ftb.envs import check_env_matches
    from torchrl_ftb.testing import MetaWorldMockEnv, make_toy_dataset

    with pytest.raises(ValueError, match="obs_dim=39"):
        check_env_matches(MetaWorldMockEnv, make_toy_dataset(num_trajectories=4, horizon=8), name="mock")
    # a locomotion env without the dataset kind
    with pytest.raises(ValueError, match="kind="):
        recipe.run(_cfg(tmp_path / "d", "env.name=hopper"))


@pytest.mark.parametrize("pairing, changed", [("diffuser.pair_neighbours=3", "diffuser.pair_neighbours=5"),
                                              ("diffuser.top_block_pairs=true", "diffuser.top_block_pairs=false")])
def test_pair_options_train_the_diffuser_and_lock_its_stage(tmp_path, pairing, changed):
    """``diffuser.pair_neighbours`` / ``top_block_pairs``: the diffuser trains on start-matched pairs / also on the
    top block's own; the option belongs to its stage."""
    recipe = _recipe()
    out = recipe.run(_cfg(tmp_path, "stop_after=diffuser", pairing))
    assert out["stopped_after"] == "diffuser" and (tmp_path / "checkpoints" / "diffuser").is_dir()
    with pytest.raises(ValueError, match="different config"):  # a changed pairing means another diffuser
        recipe.run(_cfg(tmp_path, "resume=true", changed))
    redone = recipe.run(_cfg(tmp_path, "resume=true", "redo_from=diffuser", "stop_after=diffuser"))
    assert redone["stopped_after"] == "diffuser"


def test_active_query_labels_stage(tmp_path):
    """``labels.query.strategy=entropy``: the labels stage asks in rounds and records how."""
    recipe = _recipe()
    recipe.run(_cfg(tmp_path, "stop_after=labels", "labels.query.strategy=entropy", "labels.query.initial=10",
                    "labels.query.per_round=10", "labels.query.steps=10"))
    stages = json.loads((tmp_path / "stages.json").read_text())
    assert stages["labels"]["query"] == "entropy" and stages["labels"]["num_pairs"] == 30
    from torchrl_ftb.data.labels import load_labels

    labels, meta = load_labels(tmp_path / "checkpoints" / "labels")
    pairs = {tuple(sorted(p)) for p in zip(labels["index0"].tolist(), labels["index1"].tolist(), strict=True)}
    assert len(pairs) == 30 and meta["query"]["strategy"] == "entropy"


def test_stop_rule_horizon_reaches_teacher_score_model_and_checkpoint(tmp_path):
    """``labels.horizon`` / ``score_model.horizon``: the teacher and s_psi both use the stop-rule fill."""
    recipe = _recipe()
    out = recipe.run(_cfg(tmp_path, "stop_after=blocks", "labels.horizon=20", "score_model.horizon=20"))
    stages = json.loads((tmp_path / "stages.json").read_text())
    assert stages["labels"]["teacher"] == "return(horizon=20)"
    saved = torch.load(tmp_path / "checkpoints" / "score_model.pt", weights_only=True)
    assert saved["hparams"]["horizon"] == 20 and out["score_quality"]["spearman_return"] > 0.5


def test_stop_after_a_stage_then_resume_to_the_end(tmp_path):
    """``stop_after=blocks``: preference augmentation alone (partial metrics, no diffuser);
    a later ``resume=true`` run continues from the saved stages instead of redoing them."""
    recipe = _recipe()
    run_dir = tmp_path / "run"
    with pytest.raises(ValueError, match="stop_after='sampling': not a stage"):
        recipe.run(_cfg(run_dir, "stop_after=sampling"))
    partial = recipe.run(_cfg(run_dir, "stop_after=blocks"))
    assert partial["stopped_after"] == "blocks" and partial["score_quality"]["spearman_return"] > 0.5
    stages = json.loads((run_dir / "stages.json").read_text())
    assert stages["blocks"]["done"] and "diffuser" not in stages
    assert (run_dir / "metrics_partial.json").is_file() and not (run_dir / "metrics.json").exists()
    score_mtime = (run_dir / "checkpoints" / "score_model.pt").stat().st_mtime_ns
    metrics = recipe.run(_cfg(run_dir, "resume=true"))
    assert (run_dir / "checkpoints" / "score_model.pt").stat().st_mtime_ns == score_mtime  # loaded, not retrained
    assert metrics["eval"]["num_episodes"] == 2 and metrics["score_quality"] == partial["score_quality"]
    assert (run_dir / "metrics.json").is_file() and not (run_dir / "metrics_partial.json").exists()


def test_resume_with_more_diffuser_steps_trains_on_and_redoes_the_flow(tmp_path):
    """A finished run resumed with a larger ``diffuser.steps`` trains its diffuser on from the last checkpoint to
    the very weights a run of that length gets, and redoes the flow and later stages; the earlier stages are
    kept. A smaller number is refused and leaves the run as it was."""
    from torchrl_ftb.diffusion import load_diffuser

    recipe = _recipe()
    run_dir, fresh = tmp_path / "run", tmp_path / "fresh"
    short = recipe.run(_cfg(run_dir, "diffuser.steps=20"))
    score_mtime = (run_dir / "checkpoints" / "score_model.pt").stat().st_mtime_ns
    longer = recipe.run(_cfg(run_dir, "resume=true", "diffuser.steps=40"))
    assert longer["diffuser"]["resumed_from"] == 20 and longer["diffuser"]["steps"] == 40
    assert (run_dir / "checkpoints" / "score_model.pt").stat().st_mtime_ns == score_mtime  # kept, not retrained
    assert longer["score_quality"] == short["score_quality"] and "flow" in longer and longer["eval"]["num_episodes"] == 2
    recipe.run(_cfg(fresh, "diffuser.steps=40", "stop_after=diffuser"))
    ckpt = ("checkpoints", "diffuser", "diffuser_last.pt")
    a, b = (load_diffuser(d.joinpath(*ckpt)).state_dict() for d in (run_dir, fresh))
    assert a.keys() == b.keys() and all(torch.allclose(a[k].float(), b[k].float(), atol=1e-6) for k in a)
    stages = (run_dir / "stages.json").read_text()
    with pytest.raises(ValueError, match="trained 40 steps and cannot be shortened"):
        recipe.run(_cfg(run_dir, "resume=true", "diffuser.steps=30"))
    with pytest.raises(ValueError, match="different config: labels.num_pairs"):  # more steps, but another change
        recipe.run(_cfg(run_dir, "resume=true", "diffuser.steps=50", "labels.num_pairs=31"))
    assert (run_dir / "stages.json").read_text() == stages and (run_dir / "checkpoints" / "flow.pt").is_file()


def test_metaworld_config_is_the_paper_defaults_plus_the_fill_and_a_larger_top_k():
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        paper = compose(config_name="ftb_offline")
        ours = compose(config_name="ftb_offline_metaworld", overrides=["env.name=plate-slide-v3"])
    assert ours.score_model.horizon == ours.flow.true_return_horizon == ours.env.max_episode_steps == 500
    assert ours.flow.top_k == 200 and paper.flow.top_k == 100 and paper.score_model.horizon is None
    assert ours.flow.true_return_streak == 25 and paper.flow.true_return_streak is None  # a statistic only
    # nothing else differs from the paper's defaults
    a, b = OmegaConf.to_container(paper, resolve=False), OmegaConf.to_container(ours, resolve=False)
    a["env"]["name"] = b["env"]["name"]
    for section, key in (("score_model", "horizon"), ("flow", "top_k"), ("flow", "true_return_horizon"),
                         ("flow", "true_return_streak")):
        a[section].pop(key), b[section].pop(key)
    assert a == b


def test_readme_main_command_composes_to_the_embedded_default():
    """The README's main command (its first ``recipes/ftb_offline.py`` line) names a config and overrides that
    compose to the embedded default: generated button-press, 30 scripted labels, the ``cpu`` preset."""
    line = next(l for l in (ROOT / "README.md").read_text().splitlines()
                if l.startswith("bash scripts/setup.sh && .venv/bin/python recipes/ftb_offline.py"))
    args = line.split("recipes/ftb_offline.py", 1)[1].split()
    name = "ftb_offline"
    if args[:1] == ["--config-name"]:
        name, args = args[1], args[2:]
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name=name, overrides=args)
    assert cfg.env.name == "button-press-v3" and cfg.preset == "cpu" and cfg.labels.num_pairs == 30
    assert cfg.labels.horizon == cfg.score_model.horizon == 500 and cfg.flow.top_k == 200


def test_physical_validity_checks_compose(report_rows):
    """flow.max_frame_stack_error, flow.max_hand_model_error and flow.max_contactless_object_path: each
    rejects its own kind of broken Meta-World sample, all must pass, and none set means no extra check."""
    recipe = _recipe()
    g = torch.Generator().manual_seed(0)
    obs, act = torch.zeros(4, 6, 39), torch.rand(4, 6, 4, generator=g) * 2 - 1
    for t in range(1, 6):  # a mocap-like hand: it moves by the action / 100, the stack copies the frame
        obs[:, t, 0:3] = obs[:, t - 1, 0:3] + act[:, t - 1, :3] / 100
    obs[..., 4:7] = obs[..., 0:3] + torch.tensor([0.03, 0.0, 0.0])  # the object is pushed 3 cm ahead of the hand
    obs[:, 1:, 18:36] = obs[:, :-1, 0:18]
    data = TensorDict({"observation": obs, "action": act, "mask": torch.ones(4, 6, dtype=torch.bool)}, [4, 6])
    samples = data.clone()
    samples["observation"][1, 3, 18:21] += 0.1  # stack broken, hand path fine
    samples["observation"][2, 3:, 0:3] += 0.05  # hand (and its object) jump 5 cm; the stacked frame follows
    samples["observation"][2, 3:, 4:7] += 0.05
    samples["observation"][2, 1:, 18:36] = samples["observation"][2, :-1, 0:18]
    samples["observation"][3, :, 4] += torch.arange(6) * 0.05  # the object slides away on its own
    samples["observation"][3, 1:, 22] = samples["observation"][3, :-1, 4]
    cfg = lambda stack, hand, contact, step=None: OmegaConf.create(  # noqa: E731
        {"max_frame_stack_error": stack, "max_hand_model_error": hand, "max_contactless_object_path": contact,
         "max_hand_step": step})
    check = lambda *limits: recipe.physical_validity_fn(cfg(*limits), data)[0](samples).tolist()  # noqa: E731
    assert recipe.physical_validity_fn(cfg(None, None, None), data) == (None, {})
    assert check(0.02, None, None) == [True, False, True, True]
    hand = check(None, 0.005, None)
    assert hand[0] and hand[1] and not hand[2]
    assert check(None, None, 0.01) == [True, True, True, False]
    assert check(0.02, 0.005, 0.01) == [True, False, False, False]
    assert check(None, None, None, "1x") == [True, True, False, True]  # only the 5 cm jump outruns the data's hand
    # relative limits: a multiple of the proxy's largest value on the dataset's own trajectories
    fn, limits = recipe.physical_validity_fn(cfg(0.02, "1x", "2x"), data)
    assert limits["max_frame_stack_error"] == 0.02
    assert limits["max_hand_model_error"] < 1e-6  # the mocap-like data meets its linear hand model exactly
    real_path = metaworld_contactless_object_path(data, fit_metaworld_contact_reach(data))
    assert limits["max_contactless_object_path"] == pytest.approx(2 * float(real_path.max()))
    assert fn(samples).tolist() == [True, False, False, False]
    with pytest.raises(ValueError, match="max_frame_stack_error='2x'.*frame-stack error is 0"):
        recipe.physical_validity_fn(cfg("2x", None, None), data)
    with pytest.raises(ValueError, match="max_hand_model_error='loose'.*'<factor>x'"):
        recipe.physical_validity_fn(cfg(None, "loose", None), data)
    with pytest.raises(ValueError, match="max_hand_step='fast'.*'<factor>x'"):
        recipe.physical_validity_fn(cfg(None, None, None, "fast"), data)
    # flow.max_hand_penetration: the hand no closer to the object than the dataset's hand ever is (3 cm here)
    inside = data.clone()
    inside["observation"][1, 4, 0] += 0.025  # one step 5 mm from the object: 2.5 cm inside it
    inside["observation"][2, 4, 0] += 0.004  # 4 mm closer than the data: within a 5 mm tolerance
    deep = lambda depth: OmegaConf.create({"max_hand_penetration": depth})  # noqa: E731
    fn, limits = recipe.physical_validity_fn(deep(0.005), data)
    assert limits["closest_approach"] == pytest.approx(0.03, abs=1e-6) and limits["max_hand_penetration"] == 0.005
    assert fn(inside).tolist() == [True, False, True, True]
    assert recipe.physical_validity_fn(deep(0.0), data)[0](inside).tolist() == [True, False, False, True]
    with pytest.raises(ValueError, match="max_hand_penetration='1x': give metres; real data's penetration is 0"):
        recipe.physical_validity_fn(deep("1x"), data)
    # the recipe's validity analysis: the same proxies' means over the accepted samples, the dataset beside them
    v = recipe.metaworld_validity(samples, data)
    assert v["frame_stack_error_dataset"] == 0 and v["frame_stack_error_generated"] > 0
    assert v["hand_model_error_generated"] > 10 * v["hand_model_error_dataset"]
    assert v["contactless_object_path_dataset"] < 0.01 < 0.04 < v["contactless_object_path_generated"]
    assert v["max_hand_step_dataset"] < 0.02 < 0.05 < v["max_hand_step_generated"]
    assert v["closest_approach_dataset"] == pytest.approx(0.03, abs=1e-6)
    assert v["hand_penetration_share_generated"] == 0.0 and v["hand_penetration_depth_generated"] == 0.0
    pushed = recipe.metaworld_validity(inside[1:3], data)  # 2.5 cm and 4 mm inside the data's closest
    assert pushed["closest_approach_generated"] == pytest.approx(0.005, abs=1e-6)
    assert pushed["hand_penetration_share_generated"] == 1.0
    assert pushed["hand_penetration_depth_generated"] == pytest.approx((0.025 + 0.004) / 2, abs=1e-6)
    rows = report_rows(recipe, analysis={"validity": v}, env="x")
    assert any(k.startswith("accepted samples: frame-stack") for k in rows)
    assert rows["accepted samples: closest hand-object approach, m (dataset); share closer than the dataset's hand "
                "ever comes, mean depth, m"].endswith("; 0, 0")
    still = data.clone()
    still["observation"][..., 4:7] = 0.0  # an object that never moves: no reach to fit, NaN instead of a failed run
    v = recipe.metaworld_validity(samples, still)
    assert v["contactless_object_path_generated"] != v["contactless_object_path_generated"]  # NaN
    assert v["hand_model_error_generated"] > 0



def test_oracle_validity_on_envs_with_one_step_dynamics(report_rows):
    """Toy / locomotion: the accepted samples' one-step error against the env's own dynamics, beside the
    dataset's (which obeys them); Meta-World has no such oracle and keeps its proxies."""
    from torchrl_ftb.envs import dynamics_oracle
    from torchrl_ftb.testing import make_toy_dataset

    recipe = _recipe()
    data = make_toy_dataset(num_trajectories=8, horizon=16, seed=0)
    samples = data[:4].select("observation", "action", "mask").clone()
    samples["action"] = -samples["action"]  # the observations no longer follow from the actions
    v, curve = recipe.oracle_validity(samples, data, dynamics_oracle("toy", toy_horizon=16), reference_steps=300)
    assert v["dynamics_error_dataset"] < 1e-5 < 1e-2 < v["dynamics_error_generated"]
    # the paper's reference scale: a learned one-step model errs on held-out real transitions, far less than samples
    # whose actions do not explain their observations
    assert 0 < v["dynamics_error_mlp_heldout"] < v["dynamics_error_generated"] / 5
    assert curve.shape == (16,) and curve[-1] != curve[-1] and float(curve[:-1].min()) > 1e-2  # last step: no successor
    empty, none = recipe.oracle_validity(samples[:0], data, dynamics_oracle("toy", toy_horizon=16))
    assert empty["dynamics_error_generated"] != empty["dynamics_error_generated"] and none is None  # NaN, no failure
    assert "dynamics_error_mlp_heldout" not in empty  # reference_steps=0: no model
    rows = report_rows(recipe, analysis={"validity": v}, env="toy")
    row = rows["accepted samples: one-step dynamics error per observation dim (dataset)"]
    assert row == f"{v['dynamics_error_generated']:.4g} ({v['dynamics_error_dataset']:.4g})"
    assert rows["the same of an MLP one-step model on held-out real transitions (the paper's reference)"] == \
        f"{v['dynamics_error_mlp_heldout']:.4g}"
    assert not any(k.startswith("accepted samples: frame-stack") for k in rows)
    with pytest.raises(ValueError, match="validity_reference_steps=-1"):
        recipe.validity_reference_steps(OmegaConf.create({"analysis": {"validity_reference_steps": -1}}))
    assert dynamics_oracle("button-press-v3") is None
    with pytest.raises(ValueError, match="toy_horizon"):
        dynamics_oracle("toy")


def test_hand_step_check_catches_a_seam_the_mean_hand_model_error_hides():
    """A sample held at a real start that jumps 3 cm at the seam and then moves like the data: the mean
    hand-model residual over 200 steps stays under 1 mm, so flow.max_hand_model_error passes it;
    flow.max_hand_step="1x" (the data's largest step, <= 1.8 cm here) rejects it and keeps the real paths."""
    recipe = _recipe()
    g = torch.Generator().manual_seed(1)
    h = 200
    act = torch.rand(3, h, 4, generator=g) * 2 - 1
    obs = torch.zeros(3, h, 39)
    for t in range(1, h):
        obs[:, t, 0:3] = obs[:, t - 1, 0:3] + act[:, t - 1, :3] / 100
    obs[..., 4:7] = 1.0  # an object far away that never moves
    obs[:, 1:, 18:36] = obs[:, :-1, 0:18]
    data = TensorDict({"observation": obs, "action": act, "mask": torch.ones(3, h, dtype=torch.bool)}, [3, h])
    seam = data.clone()
    seam["observation"][0, 1:, 0:3] += torch.tensor([0.03, 0.0, 0.0])  # the seam: step 0 -> 1 jumps 3 cm
    seam["observation"][0, 1:, 18:36] = seam["observation"][0, :-1, 0:18]
    cfg = OmegaConf.create({"max_hand_model_error": 0.001, "max_hand_step": None})
    assert recipe.physical_validity_fn(cfg, data)[0](seam).tolist() == [True, True, True]
    cfg.max_hand_step = "1x"
    fn, limits = recipe.physical_validity_fn(cfg, data)
    assert limits["max_hand_step"] < 0.018
    assert fn(seam).tolist() == [False, True, True]
    assert fn(data).tolist() == [True, True, True]



def test_final_table_reports_the_stop_rule_cut_beside_the_fill():
    recipe = _recipe()
    flow = {"score_mean_before": 0.0, "score_mean_after": 0.0, "flow_steps_run": 1, "flow_steps_planned": 1,
            "fraction_generated_in_final": 0.5, "true_return_mean_before": 1.0, "true_return_mean_after": 2.0,
            "true_return_horizon": 500.0, "true_return_filled_mean_before": 10.0, "true_return_filled_mean_after": 12.0}
    metrics = {"env": "x", "preset": "cpu", "teacher": "success", "wall_time_s": 1.0, "score_quality": {},
               "eval": {"return_mean": 0.0, "return_std": 0.0, "length_mean": 1.0}, "flow": flow}
    assert not any("stop-rule cut" in k for k, _ in recipe.final_table(metrics))
    flow.update(true_return_streak=25.0, true_return_filled_stop_rule_mean_before=10.0,
                true_return_filled_stop_rule_mean_after=11.0)
    rows = dict(recipe.final_table(metrics))
    assert rows["the same after the stop-rule cut (25 successes): before -> after"] == "10 -> 11"


def test_sdedit_strength_inpaint_start_and_score_guidance_reach_the_flow_sampler(tmp_path):
    """``diffuser.strength`` (flow-stage sampling): 1 samples from noise, below 1 edits the condition;
    ``diffuser.inpaint_start`` holds the first step; ``diffuser.score_guidance`` climbs s_psi on the dataset's
    normalised scale."""
    from torchrl_ftb.diffusion import make_diffuser
    from torchrl_ftb.preference import ScoreModel, score_trajectories
    from torchrl_ftb.testing import make_toy_dataset

    recipe = _recipe()
    data = make_toy_dataset(num_trajectories=8, horizon=16, seed=0).select("observation", "action", "mask")
    diffuser = make_diffuser("tiny", obs_dim=data["observation"].shape[-1], action_dim=data["action"].shape[-1],
                             horizon=16, data=data, hidden_dim=16, cond_dim=16)
    model = ScoreModel(data["observation"].shape[-1], data["action"].shape[-1], num_cells=8, seed=0)
    scores = score_trajectories(model, data)

    def make(*overrides):
        cfg = _cfg(tmp_path, *overrides)
        guide, _ = recipe.flow_guide(cfg, None, model, scores, data, None, "cpu")  # s_psi's guide: no run, no labels
        return recipe.make_sampler(cfg, diffuser, guide)

    assert make().strength == 1.0
    sampler = make("diffuser.strength=0.3")
    assert sampler.strength == 0.3
    edits = sampler(TensorDict({"condition": data[:2]}, batch_size=[2]))["sample"]
    assert edits["observation"].shape == data[:2]["observation"].shape
    assert not sampler.inpaint_start
    held = make("diffuser.inpaint_start=true")
    out = held(TensorDict({"condition": data[:2]}, batch_size=[2]))["sample"]
    torch.testing.assert_close(out["observation"][:, 0], data[:2]["observation"][:, 0], atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="diffuser.inpaint_start='yes': must be true or false"):
        recipe.inpaint_start(_cfg(tmp_path, "diffuser.inpaint_start=yes"))
    assert make().guide is None and make().guide_scale == 0.0
    guided = make("diffuser.score_guidance=0.5")
    assert guided.guide_scale == 0.5
    with torch.no_grad():  # the objective is s_psi on the flow's scale: the dataset spans [0, 1]
        hat = guided.guide(data)
    assert abs(float(hat.min())) < 1e-5 and abs(float(hat.max()) - 1.0) < 1e-5
    cond = TensorDict({"condition": data[:2]}, batch_size=[2])
    guided.generator.manual_seed(0)
    pushed = guided(cond.clone())["sample"]
    plain = make()
    plain.generator.manual_seed(0)
    assert not torch.allclose(pushed["observation"], plain(cond.clone())["sample"]["observation"])
    for bad, shown in (("-1", "-1"), ("true", "True"), ("nan", "nan")):
        with pytest.raises(ValueError, match=f"diffuser.score_guidance={shown}: must be a number >= 0"):
            recipe.score_guidance(_cfg(tmp_path, f"diffuser.score_guidance={bad}"))


def test_flow_seed_draws_other_noise_on_the_same_diffuser(tmp_path):
    """``flow.seed`` (null: the run's seed) seeds the flow sampler's noise, so a flow can be redone on the same
    diffuser with other noise (``redo_from=flow``); ``bc.seed`` and ``flow.seed`` share one check."""
    from torchrl_ftb.diffusion import make_diffuser
    from torchrl_ftb.testing import make_toy_dataset

    recipe = _recipe()
    data = make_toy_dataset(num_trajectories=4, horizon=16, seed=0).select("observation", "action", "mask")
    diffuser = make_diffuser("tiny", obs_dim=data["observation"].shape[-1], action_dim=data["action"].shape[-1],
                             horizon=16, data=data, hidden_dim=16, cond_dim=16)
    cond = TensorDict({"condition": data[:2]}, batch_size=[2])

    def draw(*overrides):
        return recipe.make_sampler(_cfg(tmp_path, *overrides), diffuser, None)(cond.clone())["sample"]["observation"]

    assert recipe.stage_seed(_cfg(tmp_path, "seed=3"), "flow") == 3  # null: the run's seed
    assert recipe.stage_seed(_cfg(tmp_path, "seed=3", "flow.seed=7"), "flow") == 7
    torch.testing.assert_close(draw("seed=3"), draw("flow.seed=3"))  # the same noise, whichever key sets it
    assert not torch.allclose(draw("seed=3"), draw("seed=3", "flow.seed=4"))
    for stage in ("flow", "bc"):
        with pytest.raises(ValueError, match=f"{stage}.seed=-1: must be a whole number >= 0, or null"):
            recipe.stage_seed(_cfg(tmp_path, f"{stage}.seed=-1"), stage)


def test_score_guidance_by_an_ensemble_and_its_pessimistic_bound(tmp_path):
    """``diffuser.score_guidance_members`` = M > 1 guides by an M-member ensemble trained once on the run's labels
    (kept beside s_psi, loaded again, retrained when M changes); ``diffuser.score_guidance_kappa`` climbs the members'
    mean minus kappa times their spread, on its own dataset span; bad settings are refused by name."""
    from types import SimpleNamespace

    from torchrl_ftb.data.labels import ReturnTeacher, make_scripted_labels
    from torchrl_ftb.diffusion import make_diffuser
    from torchrl_ftb.preference import (ScoreModel, load_score_model, normalized_scores, pessimistic_scores,
                                        score_objective, score_trajectories)
    from torchrl_ftb.testing import make_toy_dataset

    recipe = _recipe()
    full = make_toy_dataset(num_trajectories=12, horizon=16, seed=0)
    data = full.select("observation", "action", "mask")
    labels = make_scripted_labels(full, num_pairs=10, teacher=ReturnTeacher(), seed=0)
    model = ScoreModel(data["observation"].shape[-1], data["action"].shape[-1], num_cells=8, seed=0)
    scores = score_trajectories(model, data)
    run = SimpleNamespace(ckpt=tmp_path / "checkpoints")
    run.ckpt.mkdir()
    cfg = lambda *o: _cfg(tmp_path, "diffuser.score_guidance=0.3", "score_model.steps=20", *o)  # noqa: E731
    assert recipe.flow_guide(_cfg(tmp_path), run, model, scores, data, labels, "cpu") == (None, {})
    plain, summary = recipe.flow_guide(cfg(), run, model, scores, data, labels, "cpu")  # s_psi on its own span
    assert summary == {} and not (run.ckpt / recipe.GUIDE_CHECKPOINT).exists()
    torch.testing.assert_close(plain(data), normalized_scores(scores, float(scores.min()), float(scores.max())))
    bound, summary = recipe.flow_guide(cfg("diffuser.score_guidance_members=3", "diffuser.score_guidance_kappa=1"),
                                       run, model, scores, data, labels, "cpu")
    assert summary["trained"] and summary["members"] == 3 and summary["kappa"] == 1.0 and summary["steps"] == 20
    path = run.ckpt / recipe.GUIDE_CHECKPOINT
    guide = load_score_model(path)
    assert guide.num_members == 3
    members = score_trajectories(guide, data, members=True)
    assert float(members.std(0).min()) > 0  # members trained apart
    span = pessimistic_scores(guide, data, kappa=1.0)
    torch.testing.assert_close(span, members.mean(0) - members.std(0))
    assert bool((span < score_trajectories(guide, data)).all())
    with torch.no_grad():  # the bound on its own dataset span: the dataset spans [0, 1]
        hat = bound(data)
    assert abs(float(hat.min())) < 1e-5 and abs(float(hat.max()) - 1.0) < 1e-5
    torch.testing.assert_close(hat, normalized_scores(span, float(span.min()), float(span.max())))
    written = path.stat().st_mtime_ns
    mean, summary = recipe.flow_guide(cfg("diffuser.score_guidance_members=3"), run, model, scores, data, labels,
                                      "cpu")
    assert path.stat().st_mtime_ns == written and not summary["trained"]  # loaded, not retrained
    mean_scores = score_trajectories(guide, data)
    torch.testing.assert_close(mean(data), normalized_scores(mean_scores, float(mean_scores.min()),
                                                             float(mean_scores.max())))
    recipe.flow_guide(cfg("diffuser.score_guidance_members=2"), run, model, scores, data, labels, "cpu")
    assert load_score_model(path).num_members == 2 and path.stat().st_mtime_ns != written
    # the sampler climbs the objective it is given
    diffuser = make_diffuser("tiny", obs_dim=data["observation"].shape[-1], action_dim=data["action"].shape[-1],
                             horizon=16, data=data, hidden_dim=16, cond_dim=16)
    sampler = recipe.make_sampler(cfg("diffuser.score_guidance_members=3", "diffuser.score_guidance_kappa=1"),
                                  diffuser, bound)
    assert sampler.guide is bound and sampler.guide_scale == 0.3
    assert recipe.make_sampler(cfg(), diffuser, None).guide is None  # a loaded flow: no guide to build
    torch.testing.assert_close(pessimistic_scores(guide, data, kappa=0.0), score_trajectories(guide, data))
    with pytest.raises(ValueError, match="kappa=1.0 needs an ensemble"):
        score_objective(model, 0.0, 1.0, kappa=1.0)
    for overrides, message in (
            (("diffuser.score_guidance_kappa=1",), "diffuser.score_guidance_kappa=1 needs an ensemble"),
            (("diffuser.score_guidance_members=0",), "diffuser.score_guidance_members=0: must be a whole number"),
            (("diffuser.score_guidance_kappa=-1",), "diffuser.score_guidance_kappa=-1: must be a number >= 0"),
            (("diffuser.score_guidance=0", "diffuser.score_guidance_members=3"), "guides nothing without"),
            (("score_model.num_members=3", "diffuser.score_guidance_members=3"), "would be s_psi retrained")):
        with pytest.raises(ValueError, match=message):
            recipe.run(cfg(*overrides, f"run_dir={tmp_path / 'bad'}"))
        assert not (tmp_path / "bad").exists()
    # s_psi's own ensemble may be the guide's
    assert recipe.score_guidance_kappa(cfg("score_model.num_members=2", "diffuser.score_guidance_kappa=0.5")) == 0.5


def test_bc_keep_top_k_clones_the_top_k_plus_the_generated_samples(tmp_path):
    """``bc.keep_top_k``: BC's data is the original top-k plus the final set's generated trajectories (each once),
    with the generated ones flagged for ``bc.relabel_actions``; off (the paper), the final set as it is."""
    from torchrl_ftb.testing import make_toy_dataset

    recipe = _recipe()
    data = make_toy_dataset(num_trajectories=6, horizon=8, seed=0)
    original = data[:4].select("observation", "action", "mask")
    final = torch.cat([original[[0, 2]], data[4:].select("observation", "action", "mask")], 0)
    flow = {"trajectories": final, "original": original, "source_step": torch.tensor([0, 0, 2, 1])}
    paper, generated = recipe.bc_trajectories(_cfg(tmp_path), flow)
    assert paper is not None and torch.equal(paper["observation"], final["observation"])
    assert generated.tolist() == [False, False, True, True]
    kept, generated = recipe.bc_trajectories(_cfg(tmp_path, "bc.keep_top_k=true"), flow)
    assert torch.equal(kept["observation"], torch.cat([original["observation"], data[4:]["observation"]]))
    assert generated.tolist() == [False] * 4 + [True] * 2
    with pytest.raises(ValueError, match="bc.keep_top_k='yes': must be true or false"):
        recipe.run(_cfg(tmp_path / "k", "bc.keep_top_k=yes"))
    assert not (tmp_path / "k").exists()


def test_options_added_later_resume_old_run_directories_at_their_no_op_defaults():
    """A run directory written before an option existed resumes when the option is at its no-op value."""
    recipe = _recipe()
    old = {"diffuser": {"guidance": None}, "flow": {"top_k": 8}, "score_model": {}}
    new = {"diffuser": {"guidance": None, "strength": 1.0, "inpaint_start": False, "score_guidance": 0.0,
                        "score_guidance_members": 1, "score_guidance_kappa": 0.0},
           "flow": {"top_k": 8, "filter": "score_model", "ensemble_rule": "mean"},
           "score_model": {"num_members": 1}}
    assert recipe._diff_keys(new, old) == []
    new["diffuser"]["strength"] = 0.5
    assert recipe._diff_keys(new, old) == ["diffuser.strength: '<missing>' -> 0.5"]
    # an option removed since (session 31's bc.tracker_steps, now tracker.steps) resumes; another lost key does not
    old_s31, new_s32 = {"bc": {"steps": 5, "tracker_steps": 4000}}, {"bc": {"steps": 5}}
    assert recipe._diff_keys(new_s32, old_s31) == []
    assert recipe._diff_keys({"bc": {}}, old_s31) == ["bc.steps: 5 -> '<missing>'"]
    # session 52's removed hand-model penalty resumes where it was off, not where a run used it
    assert recipe._diff_keys({"diffuser": {}}, {"diffuser": {"score_guidance_hand_penalty": 0.0}}) == []
    assert recipe._diff_keys({"diffuser": {}}, {"diffuser": {"score_guidance_hand_penalty": 0.1}}) == [
        "diffuser.score_guidance_hand_penalty: 0.1 -> '<missing>'"]


def test_resume_refuses_another_tracker_under_a_half_trained_relabelled_bc(tmp_path):
    """``tracker`` may change on resume (it serves the analysis), but not while BC is half-trained on actions the
    tracker relabelled: the refitted tracker would hand BC other actions from its checkpoint on. Nothing is
    removed when refused; a finished BC, ``redo_from=bc`` or relabelling off lets it change."""
    import json

    from omegaconf import OmegaConf

    recipe = _recipe()
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    first = _cfg(run_dir, "bc.relabel_actions=true", "tracker.steps=50")
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(first, resolve=True))
    stages = {stage: {"done": True} for stage in ("dataset", "labels", "score_model", "blocks", "diffuser", "flow")}
    (run_dir / "stages.json").write_text(json.dumps(stages))
    (run_dir / "checkpoints" / "bc.pt").write_bytes(b"half-trained")
    with pytest.raises(ValueError, match="tracker.steps=60: .*bc.pt is half-trained on actions relabelled by a "
                                         "tracker of 50 steps"):
        recipe.RunDir(_cfg(run_dir, "bc.relabel_actions=true", "tracker.steps=60", "resume=true"))
    assert (run_dir / "checkpoints" / "bc.pt").is_file()
    recipe.RunDir(_cfg(run_dir, "bc.relabel_actions=true", "tracker.steps=50", "resume=true"))  # same tracker
    (run_dir / "stages.json").write_text(json.dumps({**stages, "bc": {"done": True}}))
    recipe.RunDir(_cfg(run_dir, "bc.relabel_actions=true", "tracker.steps=60", "resume=true"))  # BC finished
    (run_dir / "stages.json").write_text(json.dumps(stages))
    recipe.RunDir(_cfg(run_dir, "bc.relabel_actions=true", "tracker.steps=60", "resume=true", "redo_from=bc"))
    assert not (run_dir / "checkpoints" / "bc.pt").exists()  # redone: BC starts afresh on the new tracker's actions


def test_resume_checks_that_the_labels_and_the_dataset_are_still_the_run_s(tmp_path):
    """On resume the saved labels must still be segments of the run's dataset (``check_labels_match``) and the
    dataset the one recorded at the start: a mismatch is refused with the folder named, not trained on."""
    import json

    from torchrl_ftb.data.labels import load_labels, save_labels

    recipe = _recipe()
    run_dir = tmp_path / "run"
    recipe.run(_cfg(run_dir, "stop_after=labels"))
    label_dir = run_dir / "checkpoints" / "labels"
    labels, meta = load_labels(label_dir)
    swapped = labels.clone()
    swapped["index0"] = (labels["index0"] + 1) % 48  # the labels now name other trajectories than their segments
    save_labels(swapped, label_dir, meta=meta)
    with pytest.raises(ValueError, match=rf"{label_dir}"):
        recipe.run(_cfg(run_dir, "resume=true", "stop_after=labels"))
    save_labels(labels, label_dir, meta=meta)
    stages = json.loads((run_dir / "stages.json").read_text())
    stages["dataset"]["path"] = "/elsewhere/another-cache-entry"
    (run_dir / "stages.json").write_text(json.dumps(stages))
    with pytest.raises(ValueError, match="the dataset changed since the run started .*another-cache-entry"):
        recipe.run(_cfg(run_dir, "resume=true", "stop_after=labels"))
