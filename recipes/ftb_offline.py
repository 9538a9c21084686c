"""Flow to Better, offline (paper Alg. 1), TorchRL sota-implementation style.

    python recipes/ftb_offline.py                      # button-press-v3, 30 scripted labels, cpu preset
    python recipes/ftb_offline.py preset=paper labels.teacher=success
    python recipes/ftb_offline.py env.name=toy         # ToyLineEnv, seconds
    python recipes/ftb_offline.py env.name=hopper +dataset.options.kind=medium-replay  # D4RL-style (see config)
    python recipes/ftb_offline.py resume=true          # continue a killed run (same run_dir)

Stages (each ends with a checkpoint in ``run_dir/checkpoints`` and an entry in
``run_dir/stages.json``): dataset (generated, cached) → scripted labels → score model
``s_psi`` → blocks → trajectory diffuser (periodic checkpoints) → flow to better → BC
(periodic checkpoints) → evaluation. With ``resume=true`` finished stages are loaded,
unfinished training continues from its last checkpoint; a different config, a corrupt or
mismatched checkpoint raise a clear error and nothing is overwritten. ``resume=true`` with a larger
``diffuser.steps`` trains the run's diffuser on from its last checkpoint and redoes the flow and later
stages (on locomotion 4x the ``cpu`` preset's steps pays: BENCHMARKS.md, session 35). ``stop_after=<stage>``
stops once that stage is done (``metrics_partial.json``; e.g. ``stop_after=blocks`` for
preference augmentation alone); a later ``resume=true`` run continues from there.

The run directory receives ``config.yaml`` (resolved), ``metrics.json``, ``report.md``,
``plots/*.png`` (score and true return per flow step, before-vs-after histograms) and the
logger's files (``logs/``). The final table is printed. On generated Meta-World data the
analysis also replays the final set's generated trajectories in the simulator
(``analysis.open_loop``: ``open_loop.json`` and a claimed-vs-replayed scatter), so the table gives
the true return the simulator gives beside the one read off the generated states.

Envs, datasets, true rewards and scores come from ``torchrl_ftb.envs`` (``make_env``,
``true_reward_fn``, ``normalized_score_fn``) and ``torchrl_ftb.datasets`` (``make_dataset``):
toy, Meta-World v3 (success rate) and locomotion (D4RL-normalized score; ``eval.stop_on_success``
is ignored there).
"""
from __future__ import annotations

import functools
import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase

from torchrl_ftb.analysis import (
    check_readers,
    dynamics_error,
    fit_dynamics_reference,
    locomotion_open_loop_improvement,
    locomotion_tracked_improvement,
    novelty,
    open_loop_improvement,
    per_step_mean,
    plot_curves,
    plot_flow_curves,
    plot_histograms,
    plot_scatter,
    tracked_improvement,
)
from torchrl_ftb.data import atomic_torch_save, atomic_write_text, read_checkpoint, trajectories_to_flat
from torchrl_ftb.data.labels import SuccessTeacher, check_labels_match, load_labels, make_teacher, save_labels
from torchrl_ftb.datasets import dataset_kwargs, make_dataset
from torchrl_ftb.diffusion import DiffusionSampler, load_diffuser, make_diffuser, run_settings, train_diffuser
from torchrl_ftb.diffusion.train import CHECKPOINT_NAME
from torchrl_ftb.envs import (
    METAWORLD_PHYSICS_PROXIES,
    check_env_matches,
    dynamics_oracle,
    env_kind,
    fit_metaworld_contact_reach,
    fit_metaworld_hand_model,
    make_env,
    metaworld_closest_approach,
    metaworld_contact_check,
    metaworld_contactless_object_path,
    metaworld_frame_stack_check,
    metaworld_hand_model_check,
    metaworld_hand_model_error,
    metaworld_hand_penetration,
    metaworld_hand_step_check,
    metaworld_max_hand_step,
    metaworld_penetration_check,
    metaworld_physics_errors,
    normalized_score_fn,
    observation_layout,
    physics_limit,
    true_reward_fn,
)
from torchrl_ftb.flow import FlowToBetter, check_flow_options, true_return_score
from torchrl_ftb.policy import (
    PathTracker,
    check_policy_sections,
    evaluate_policy,
    fit_path_tracker,
    load_bc_checkpoint,
    make_bc_actor_for,
    make_transition_buffer,
    train_bc,
)
from torchrl_ftb.preference import (
    ScoreModel,
    QUERY_STRATEGIES,
    load_score_model,
    save_score_model,
    correlations,
    make_query_labels,
    make_block_pair_buffer,
    make_blocks,
    pessimistic_scores,
    score_objective,
    score_trajectories,
    top_k_mean,
    train_score_model,
)
from torchrl_ftb.provenance import git_commit, machine_info, make_logger, write_json

#: flow.filter: what ranks the top-k, accepts samples and ranks the final set (true_return: an oracle bound)
FLOW_FILTERS = ("score_model", "true_return")
STAGES = ("dataset", "labels", "score_model", "blocks", "diffuser", "flow", "bc", "eval")
#: the score guide's own ensemble (``diffuser.score_guidance_members`` > 1), under ``checkpoints/``
GUIDE_CHECKPOINT = "guide_score_model.pt"
# config entries that may change between a killed run and its resume
# (analysis: recomputed at every run's end, never checkpointed)
RESUME_FREE_KEYS = ("resume", "overwrite", "redo_from", "stop_after", "progress", "logger", "device", "run_dir",
                    "hydra", "analysis", "tracker")
#: entries of another stage's section that only a later stage reads (free when that one is redone):
#: the diffuser's sampling settings are used by the flow only
STAGE_OWNED_KEYS = {"flow": (("diffuser", "sampler"), ("diffuser", "sample_steps"), ("diffuser", "guidance"),
                              ("diffuser", "strength"), ("diffuser", "inpaint_start"), ("diffuser", "score_guidance"),
                              ("diffuser", "score_guidance_members"), ("diffuser", "score_guidance_kappa"),
                              ("diffuser", "score_guidance_hand_penalty"))}  # the last: removed, old runs
#: what each stage leaves under ``checkpoints/`` (removed by ``redo_from``); the path tracker depends on the
#: dataset only (:func:`path_tracker`), the score guide's ensemble on the labels and s_psi's settings
#: (:func:`flow_guide`)
STAGE_CHECKPOINTS = {"dataset": ("tracker.pt",), "labels": ("labels",),
                     "score_model": ("score_model.pt", GUIDE_CHECKPOINT), "blocks": ("blocks.pt",),
                     "diffuser": ("diffuser",), "flow": ("flow.pt",), "bc": ("bc.pt",)}


# ====================================================================
# Run directory bookkeeping
# -------------------------


def _comparable(cfg: DictConfig) -> dict:
    full = OmegaConf.to_container(cfg, resolve=True)
    return {k: v for k, v in full.items() if k not in RESUME_FREE_KEYS}


#: options added after runs were saved, with the value that reproduces the older behaviour
_ADDED_OPTION_NOOPS = {"score_model.num_members": 1, "flow.ensemble_rule": "mean", "flow.filter": "score_model",
                       "diffuser.strength": 1.0, "diffuser.score_guidance": 0.0, "bc.keep_top_k": False,
                       "diffuser.score_guidance_members": 1, "diffuser.score_guidance_kappa": 0.0}


_ANY = object()
#: options removed since runs were saved (a saved config may still hold them), with the saved value that resumes
#: (``_ANY``: whatever it was): session 31's two tracker_steps, now the one ``tracker.steps``; session 52's hand-model
#: penalty of the score guide, removed after it was measured not to help (a run that used it resumes only with
#: ``redo_from=flow`` or earlier, the stage that read it)
_REMOVED_OPTIONS = {"bc.tracker_steps": _ANY, "diffuser.score_guidance_hand_penalty": 0.0}


def _diff_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    """Differences ``old -> new`` between config ``a`` (new) and ``b`` (saved); a key the saved
    config lacks matches an empty new value or its ``_ADDED_OPTION_NOOPS`` entry (an option
    added later, left at its no-op default); a saved key in ``_REMOVED_OPTIONS`` is ignored at its listed value."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b), key=str):
            out += _diff_keys(a.get(k, "<missing>"), b.get(k, "<missing>"), f"{prefix}{k}.")
        return out
    if a == "<missing>" and _REMOVED_OPTIONS.get(prefix[:-1], "<none>") in (_ANY, b):
        return []
    if b == "<missing>" and (a is None or a is False or a == {} or a == []
                             or _ADDED_OPTION_NOOPS.get(prefix[:-1], "<none>") == a):
        return []
    return [] if a == b else [f"{prefix[:-1]}: {b!r} -> {a!r}"]


def _drop_keys(config: dict, keys: list[tuple[str, str]]) -> dict:
    """``config`` without the ``(section, entry)`` pairs in ``keys`` (sections copied, not mutated)."""
    out = dict(config)
    for section, entry in keys:
        if isinstance(out.get(section), dict):
            out[section] = {k: v for k, v in out[section].items() if k != entry}
    return out


class RunDir:
    """Stage markers (``stages.json``), resolved config and checkpoint paths of one run."""

    def __init__(self, cfg: DictConfig) -> None:
        self.path = Path(cfg.run_dir).expanduser().resolve()
        self.ckpt = self.path / "checkpoints"
        self.stages_file = self.path / "stages.json"
        self.config_file = self.path / "config.yaml"
        self.resume = bool(cfg.resume)
        started = self.stages_file.exists() or self.ckpt.exists()
        if started and not self.resume:
            if not cfg.overwrite:
                raise ValueError(
                    f"{self.path}: run directory already holds a run; pass resume=true to continue it, "
                    "overwrite=true to start again, or another run_dir"
                )
            shutil.rmtree(self.ckpt, ignore_errors=True)
            for name in ("stages.json", "metrics.json", "report.md"):
                (self.path / name).unlink(missing_ok=True)
        self.stages: dict[str, dict] = {}
        if self.resume and self.stages_file.exists():
            try:
                self.stages = json.loads(self.stages_file.read_text())
            except json.JSONDecodeError as err:
                raise ValueError(f"{self.stages_file}: corrupt stage file ({err})") from err
        redo = cfg.get("redo_from")
        if redo is not None:
            if redo not in STAGES:
                raise ValueError(f"redo_from={redo!r}: not a stage; choose one of {list(STAGES)}")
            if not self.resume:
                raise ValueError("redo_from needs resume=true (it redoes the later stages of an existing run)")
        extension = None
        if self.resume and self.config_file.exists():
            old = OmegaConf.to_container(OmegaConf.load(self.config_file), resolve=True)
            # the config sections of redone stages may change (that is what redo_from is for)
            free = set(RESUME_FREE_KEYS) | (set(STAGES[STAGES.index(redo):]) if redo is not None else set())
            self._check_relabelling_tracker(cfg, old, free)
            owned = [key for stage in free for key in STAGE_OWNED_KEYS.get(stage, ())]
            extension = None if "diffuser" in free else self._diffuser_extension(cfg, old)
            if extension is not None:
                owned.append(("diffuser", "steps"))
            old = _drop_keys({k: v for k, v in old.items() if k not in free}, owned)
            new_cfg = _drop_keys({k: v for k, v in _comparable(cfg).items() if k not in free}, owned)
            diff = _diff_keys(new_cfg, old)
            if diff:
                raise ValueError(f"{self.config_file}: resume=true with a different config: " + "; ".join(diff))
        # only now, with the config accepted, is anything of the old run removed
        if redo is not None:
            self._forget(redo)
        if extension is not None:
            self._forget("diffuser", keep=("diffuser",))
            print(extension, flush=True)
        self.path.mkdir(parents=True, exist_ok=True)
        self.ckpt.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.config_file, OmegaConf.to_yaml(cfg, resolve=True))

    def _check_relabelling_tracker(self, cfg: DictConfig, old: dict, free: set) -> None:
        """``tracker`` is free on resume (it serves the analysis), except while BC is half-trained on actions the
        tracker relabelled (``bc.relabel_actions``): a changed ``tracker.steps`` would refit it and BC would go on
        from its checkpoint on other actions. Raise instead, before anything is removed."""
        bc_half_done = (self.ckpt / "bc.pt").is_file() and not self.done("bc") and "bc" not in free
        if not bc_half_done or not bool((old.get("bc") or {}).get("relabel_actions", False)):
            return
        before, now = tracker_steps(old), tracker_steps(cfg)
        if before != now:
            raise ValueError(f"tracker.steps={now}: {self.ckpt / 'bc.pt'} is half-trained on actions relabelled by a "
                             f"tracker of {before} steps (bc.relabel_actions); keep tracker.steps={before} or pass "
                             f"redo_from=bc")

    def _diffuser_extension(self, cfg: DictConfig, old: dict) -> str | None:
        """Whether ``resume=true`` asks for more diffuser training than the run's config did (a message saying so;
        ``None``: it does not). Then the diffuser trains on from its last checkpoint up to the new total (as an
        uninterrupted run of that length would), and the flow and every later stage are redone; the dataset,
        labels, score model and blocks are kept. A number below what the diffuser has trained raises (a trained
        diffuser cannot be shortened; ``redo_from=diffuser`` trains a new one)."""
        saved = old.get("diffuser") or {}
        if saved.get("preset") != cfg.diffuser.preset:  # another model: the config comparison reports it
            return None
        before = run_settings(str(saved["preset"]), steps=saved.get("steps"))["steps"]
        steps = diffuser_settings(cfg)["steps"]
        if steps == before:
            return None
        path = self.ckpt / "diffuser" / CHECKPOINT_NAME
        if self.done("diffuser"):
            trained = int(self.stages["diffuser"]["steps"])
        else:  # killed during training (or not started): the last checkpoint's step
            trained = int(read_checkpoint(path, what="diffuser")["step"]) if path.is_file() else 0
        if steps < trained:
            raise ValueError(f"diffuser.steps={steps}: the diffuser of {self.path} has trained {trained} steps and "
                             f"cannot be shortened; pass redo_from=diffuser to train a new one")
        return f"diffuser.steps {before} -> {steps}: training on from step {trained}; the flow and later stages are redone"

    def _forget(self, first: str, *, keep: tuple[str, ...] = ()) -> None:
        """Mark stage ``first`` and every later one undone and remove their checkpoints (not those of ``keep``)."""
        later = STAGES[STAGES.index(first):]
        for name in later:
            self.stages.pop(name, None)
        if self.stages_file.exists():  # first: a kill while deleting must not leave a stage done without its files
            write_json(self.stages_file, self.stages)
        for name in later:
            for item in () if name in keep else STAGE_CHECKPOINTS.get(name, ()):
                target = self.ckpt / item
                shutil.rmtree(target) if target.is_dir() else target.unlink(missing_ok=True)

    def done(self, stage: str) -> bool:
        return bool(self.stages.get(stage, {}).get("done"))

    def mark(self, stage: str, **summary: Any) -> None:
        self.stages[stage] = {"done": True, **summary}
        write_json(self.stages_file, self.stages)


def _load_ckpt(path: Path, kind: str) -> dict:
    """``torch.load(weights_only=True)`` with a clear error for missing/corrupt/foreign files."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint missing although stages.json marks it done")
    ckpt = read_checkpoint(path)
    if not isinstance(ckpt, dict) or ckpt.get("kind") != kind:
        raise ValueError(f"{path}: not a {kind} checkpoint")
    return ckpt


def _td_to_ckpt(td: TensorDict) -> dict:
    return {"data": td.to_dict(), "batch_size": list(td.batch_size)}


def _td_from_ckpt(d: dict, path: Path, key: str) -> TensorDict:
    try:
        return TensorDict(d[key]["data"], batch_size=d[key]["batch_size"])
    except Exception as err:
        raise ValueError(f"{path}: malformed entry {key!r} ({err})") from err


# ====================================================================
# Stages
# ------


def make_score_model(cfg, obs_dim: int, act_dim: int, device) -> ScoreModel:
    """The untrained score model of ``cfg.score_model`` (seeded by ``cfg.seed``)."""
    sm_cfg = cfg.score_model
    return ScoreModel(obs_dim, act_dim, num_cells=int(sm_cfg.num_cells), num_layers=int(sm_cfg.num_layers),
                      gamma=float(sm_cfg.gamma), num_members=int(sm_cfg.get("num_members", 1)),
                      reward_activation=str(sm_cfg.get("reward_activation", "identity")),
                      horizon=_optional_int(sm_cfg.get("horizon")), seed=int(cfg.seed), device=device)


def _optional_int(value) -> int | None:
    return None if value is None else int(value)


def fit_score_model(cfg, model: ScoreModel, trajs, labels, device, logger=None) -> dict:
    """Fit ``model``'s observation normaliser (if configured) and train it on ``labels`` as ``cfg`` says."""
    sm_cfg = cfg.score_model
    if sm_cfg.get("normalize_observations"):
        model.fit_normalizer(trajs)  # on the whole dataset, not the labelled trajectories
    return train_score_model(
        model, labels, steps=int(sm_cfg.steps), batch_size=int(sm_cfg.batch_size), lr=float(sm_cfg.lr),
        eval_fraction=float(sm_cfg.eval_fraction), seed=int(cfg.seed), logger=logger,
        progress=bool(cfg.progress), device=device,
    )


def stage_score_model(cfg, run: RunDir, trajs, labels, obs_dim, act_dim, device, logger) -> ScoreModel:
    model = make_score_model(cfg, obs_dim, act_dim, device)
    path = run.ckpt / "score_model.pt"
    if run.done("score_model"):
        return load_score_model(path, model=model, map_location=device)
    out = fit_score_model(cfg, model, trajs, labels, device, logger)
    save_score_model(model, path)
    run.mark("score_model", **{k: v for k, v in out.items() if isinstance(v, (int, float)) and math.isfinite(v)})
    return model


def stage_blocks(cfg, run: RunDir, trajs, model) -> tuple[torch.Tensor, torch.Tensor]:
    path = run.ckpt / "blocks.pt"
    n = trajs.batch_size[0]
    if run.done("blocks"):
        ckpt = _load_ckpt(path, "torchrl_ftb.blocks")
        scores, ids = ckpt.get("scores"), ckpt.get("block_ids")
        if not isinstance(scores, torch.Tensor) or scores.shape != (n,) or ids.shape != (n,):
            raise ValueError(f"{path}: blocks checkpoint does not match the dataset of {n} trajectories")
        return scores, ids
    scores = score_trajectories(model, trajs).cpu()
    ids = make_blocks(scores, int(cfg.blocks.num_blocks), seed=int(cfg.seed))
    atomic_torch_save({"kind": "torchrl_ftb.blocks", "scores": scores, "block_ids": ids}, path)
    sizes = torch.bincount(ids).tolist()
    run.mark("blocks", num_blocks=int(ids.max()) + 1, block_sizes=sizes)
    return scores, ids


def diffuser_settings(cfg: DictConfig) -> dict:
    """Training/sampling numbers: the config's, or the diffusion preset's where the config says null."""
    d = cfg.diffuser
    return run_settings(str(d.preset), steps=d.steps, batch_size=d.batch_size, lr=d.lr, grad_clip=d.grad_clip,
                        sampler=d.sampler, sample_steps=d.sample_steps, guidance=d.guidance)


def make_sampler(cfg, diffuser, guide: Callable[[TensorDictBase], torch.Tensor] | None) -> DiffusionSampler:
    """The flow's sampler; with ``diffuser.score_guidance`` its samples are pushed up ``guide`` (:func:`flow_guide`;
    None: no guide) by that scale. The guide's step is normalised, so the objective's scale changes nothing it
    samples; and it climbs its objective whatever ``flow.filter`` and ``flow.ensemble_rule`` accept by."""
    s = diffuser_settings(cfg)
    # a generator (not ``seed=``): every flow step must draw fresh noise, reproducibly
    device = diffuser.normalizer.mean.device
    generator = torch.Generator(device=device).manual_seed(stage_seed(cfg, "flow"))
    scale = score_guidance(cfg) if guide is not None else 0.0
    return DiffusionSampler(diffuser, sampler=s["sampler"], steps=s["sample_steps"], guidance=s["guidance"],
                            strength=sdedit_strength(cfg), inpaint_start=inpaint_start(cfg), generator=generator,
                            autocast_bf16=bool(cfg.diffuser.autocast_bf16), guide=guide if scale else None,
                            guide_scale=scale)


def score_guidance(cfg: DictConfig) -> float:
    """``diffuser.score_guidance`` >= 0: 0 (the paper) samples by classifier-free guidance alone; lambda > 0 also
    moves each sampler step's predicted clean sample up s_psi's gradient
    (:meth:`~torchrl_ftb.diffusion.TrajectoryDiffuser.objective_guide`)."""
    return number_option(cfg, "diffuser.score_guidance", 0.0, within=lambda v: math.isfinite(v) and v >= 0,
                         expected="a number >= 0 (0: none, the paper; lambda: each sampler step also climbs s_psi's "
                                  "gradient)")


def score_guidance_members(cfg: DictConfig) -> int:
    """``diffuser.score_guidance_members``: 1 (default) guides by s_psi itself; M > 1 by an M-member ensemble of
    score models trained on the run's labels with s_psi's settings (:func:`flow_guide`). Needs score guidance."""
    value = OmegaConf.select(cfg, "diffuser.score_guidance_members", default=1)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"diffuser.score_guidance_members={value!r}: must be a whole number >= 1 (1: s_psi itself)")
    if value > 1 and not score_guidance(cfg):
        raise ValueError(f"diffuser.score_guidance_members={value} guides nothing without diffuser.score_guidance > 0")
    if value > 1 and value == int(OmegaConf.select(cfg, "score_model.num_members", default=1)):
        raise ValueError(f"diffuser.score_guidance_members={value} equals score_model.num_members: with s_psi's "
                         f"settings and seed the guide would be s_psi retrained; set it to 1 (s_psi itself)")
    return value


def score_guidance_kappa(cfg: DictConfig) -> float:
    """``diffuser.score_guidance_kappa`` >= 0: the guide climbs its ensemble's mean minus kappa times the members'
    spread (0: the mean). Needs score guidance and an ensemble (``diffuser.score_guidance_members`` > 1, or
    ``score_model.num_members`` > 1 when the guide is s_psi)."""
    kappa = number_option(cfg, "diffuser.score_guidance_kappa", 0.0, within=lambda v: math.isfinite(v) and v >= 0,
                          expected="a number >= 0 (0: the ensemble's mean)")
    if kappa and not score_guidance(cfg):
        raise ValueError(f"diffuser.score_guidance_kappa={kappa:g} guides nothing without diffuser.score_guidance > 0")
    members = score_guidance_members(cfg)
    members = members if members > 1 else int(OmegaConf.select(cfg, "score_model.num_members", default=1))
    if kappa and members < 2:
        raise ValueError(f"diffuser.score_guidance_kappa={kappa:g} needs an ensemble to be pessimistic over: set "
                         f"diffuser.score_guidance_members > 1 (or score_model.num_members > 1)")
    return kappa


def flow_guide(cfg: DictConfig, run: RunDir, model: ScoreModel, scores: torch.Tensor, trajs: TensorDictBase,
               labels: TensorDictBase, device) -> tuple[Callable[[TensorDictBase], torch.Tensor] | None, dict]:
    """The objective the flow's sampler climbs with ``diffuser.score_guidance`` (None without) and a summary of the
    guide's own ensemble (empty when the guide is s_psi).

    The objective is a score model's score on the dataset's normalised scale (:func:`score_objective`; ``scores``:
    s_psi's on the dataset), pessimistic by ``diffuser.score_guidance_kappa``. The model is s_psi itself, or with
    ``diffuser.score_guidance_members`` = M > 1 an M-member ensemble trained on the run's labels with s_psi's
    settings, kept in ``checkpoints/guide_score_model.pt`` for the last member count (loaded onto ``device``,
    retrained when the count changes; ``redo_from=score_model`` or earlier removes it). s_psi still ranks the
    top-k, the blocks and the acceptance: the ensemble only steers the samples. One score model's gradient leads
    into directions it rewards and the task does not (BENCHMARKS #5, session 53); an ensemble's bound does not
    reward where its members disagree."""
    if not score_guidance(cfg):
        return None, {}
    members, kappa = score_guidance_members(cfg), score_guidance_kappa(cfg)
    guide, summary = model, {}
    if members > 1:
        guide_cfg = OmegaConf.merge(cfg, {"score_model": {"num_members": members}})
        guide = make_score_model(guide_cfg, trajs["observation"].shape[-1], trajs["action"].shape[-1], device)
        path = run.ckpt / GUIDE_CHECKPOINT
        summary = {"members": members, "kappa": kappa}
        try:
            load_score_model(path, model=guide, map_location=device)
            summary["trained"] = False
        except (FileNotFoundError, ValueError):  # none yet, or another member count: train it
            out = fit_score_model(guide_cfg, guide, trajs, labels, device)
            save_score_model(guide, path)
            summary.update(trained=True, **{k: v for k, v in out.items()
                                            if isinstance(v, (int, float)) and math.isfinite(v)})
    span = scores if guide is model and not kappa else pessimistic_scores(guide, trajs, kappa=kappa)
    return score_objective(guide, float(span.min()), float(span.max()), kappa=kappa), summary


def number_option(cfg: DictConfig, key: str, default: float, *, within: Callable[[float], bool],
                  expected: str) -> float:
    """The number option ``key`` (absent: ``default``) when ``within`` it, or a clear error naming it and what it
    must be (``expected``); :func:`switch`'s twin for numbers."""
    value = OmegaConf.select(cfg, key, default=default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not within(float(value)):
        raise ValueError(f"{key}={value!r}: must be {expected}")
    return float(value)


def switch(cfg: DictConfig, key: str) -> bool:
    """The on/off option ``key`` (e.g. ``"diffuser.inpaint_start"``; absent: off), or a clear error naming it."""
    value = OmegaConf.select(cfg, key, default=False)
    if not isinstance(value, bool):
        raise ValueError(f"{key}={value!r}: must be true or false")
    return value


def inpaint_start(cfg: DictConfig) -> bool:
    """``diffuser.inpaint_start``: each flow sample starts where its condition starts (not the paper's)."""
    return switch(cfg, "diffuser.inpaint_start")


def top_block_pairs(cfg: DictConfig) -> bool:
    """``diffuser.top_block_pairs``: also train on pairs inside the top block, condition below target by s_psi
    (:class:`~torchrl_ftb.preference.BlockPairSampler` ``top_block_scores``; not the paper's)."""
    return switch(cfg, "diffuser.top_block_pairs")


def sdedit_strength(cfg: DictConfig) -> float:
    """``diffuser.strength`` in (0, 1]: 1 samples from noise (the paper); below 1 each flow sample is an
    SDEdit edit of its condition (:class:`~torchrl_ftb.diffusion.DiffusionSampler`)."""
    return number_option(cfg, "diffuser.strength", 1.0, within=lambda v: 0.0 < v <= 1.0,
                         expected="a number in (0, 1] (1: sample from noise, the paper; below 1: an SDEdit edit of "
                                  "the condition)")


def pair_neighbours(cfg: DictConfig) -> int | None:
    """``diffuser.pair_neighbours``: None (the paper's uniform block pairs) or m >= 1 (each condition paired with
    the m next-block trajectories that start nearest to it; :class:`~torchrl_ftb.preference.BlockPairSampler`)."""
    value = cfg.diffuser.get("pair_neighbours")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"diffuser.pair_neighbours={value!r}: must be null or an integer >= 1")
    return int(value)


def stage_diffuser(cfg, run: RunDir, trajs, scores, block_ids, obs_dim, act_dim, device, logger):
    d = cfg.diffuser
    horizon = int(trajs.batch_size[1])
    overrides = {} if d.overrides is None else OmegaConf.to_container(d.overrides, resolve=True)
    if d.get("observation_structure"):
        layout = observation_layout(str(cfg.env.name))
        if not layout:
            raise ValueError(f"diffuser.observation_structure=true: no known observation structure for env "
                             f"{cfg.env.name!r} (only Meta-World's stacked frames and goal)")
        overrides = {**layout, **overrides}
    # data=: fits the normaliser on the dataset's valid steps and leaves its constant dims undiffused
    diffuser = make_diffuser(str(d.preset), obs_dim=obs_dim, action_dim=act_dim, horizon=horizon, data=trajs,
                             **overrides).to(device)
    ckpt_dir = run.ckpt / "diffuser"
    path = ckpt_dir / CHECKPOINT_NAME
    if run.done("diffuser"):
        return load_diffuser(path, diffuser=diffuser, map_location=device), run.stages["diffuser"]
    s = diffuser_settings(cfg)
    # a score_condition diffuser also reads each condition's dataset-normalised score
    buffer = make_block_pair_buffer(trajs, block_ids, batch_size=s["batch_size"], seed=int(cfg.seed),
                                    scores=scores if diffuser.score_condition else None,
                                    neighbours=pair_neighbours(cfg),
                                    top_block_scores=scores if top_block_pairs(cfg) else None)
    out = train_diffuser(
        diffuser, buffer, steps=s["steps"], lr=s["lr"], grad_clip=s["grad_clip"], logger=logger,
        checkpoint_dir=ckpt_dir, checkpoint_every=int(d.checkpoint_every), resume=run.resume,
        progress=bool(cfg.progress), device=device, autocast_bf16=bool(d.autocast_bf16), seed=int(cfg.seed),
    )
    summary = {"steps": out["step"], "resumed_from": out["resumed_from"], "final_loss": out["final_loss"],
               "wall_time_s": out["wall_time_s"]}
    run.mark("diffuser", **summary)
    return diffuser, summary


#: The flow's optional Meta-World physics checks (``flow.<key>``) and what each one checks, for errors.
PHYSICS_LIMIT_KEYS = {"max_frame_stack_error": "stacked previous frame", "max_hand_model_error": "mocap hand",
                      "max_contactless_object_path": "hand-object contact", "max_hand_step": "hand speed",
                      "max_hand_penetration": "hand inside the object"}
#: physics limits whose proxy is exactly 0 on real data by construction: metres only, as a multiple would reject all
_ZERO_ON_DATA_LIMITS = {"max_frame_stack_error": "real data's frame-stack error is 0",
                        "max_hand_penetration": "real data's penetration is 0 by definition (the data's closest "
                                                "approach is the reference)"}


def check_physics_limit_specs(f) -> None:
    """Raise a clear error for a malformed ``flow.max_*`` physics limit (see :func:`physical_validity_fn`)."""
    for key in PHYSICS_LIMIT_KEYS:
        spec = f.get(key)
        if isinstance(spec, str) and key in _ZERO_ON_DATA_LIMITS:
            raise ValueError(f"flow.{key}={spec!r}: give metres; {_ZERO_ON_DATA_LIMITS[key]}, so a "
                             f"multiple of it would reject every sample")
        if spec is not None:
            physics_limit(spec, torch.ones(1), field=f"flow.{key}")


def physical_validity_fn(f, trajs) -> tuple[Callable[[TensorDictBase], torch.Tensor] | None, dict[str, float]]:
    """The flow's optional Meta-World physics checks (``flow.max_frame_stack_error``,
    ``flow.max_hand_model_error``, ``flow.max_contactless_object_path``, ``flow.max_hand_step``,
    ``flow.max_hand_penetration``; the hand model, the hand's reach and its closest approach to the object are
    fitted on the dataset), all of which must pass, and their limits in metres.

    The hand-model, contact and hand-step limits may be relative, ``"<f>x"``: ``f`` times the largest value
    of the proxy over the dataset's trajectories (:func:`torchrl_ftb.envs.physics_limit`). The
    frame-stack and penetration limits are metres only (real data: exactly 0)."""
    check_physics_limit_specs(f)
    checks, limits = [], {}
    if f.get("max_frame_stack_error") is not None:
        limits["max_frame_stack_error"] = physics_limit(f.max_frame_stack_error, torch.zeros(0),
                                                        field="flow.max_frame_stack_error")
        checks.append(metaworld_frame_stack_check(limits["max_frame_stack_error"]))
    if f.get("max_hand_model_error") is not None:
        weights = fit_metaworld_hand_model(trajs)
        limits["max_hand_model_error"] = physics_limit(
            f.max_hand_model_error, metaworld_hand_model_error(trajs, weights), field="flow.max_hand_model_error")
        checks.append(metaworld_hand_model_check(weights, limits["max_hand_model_error"]))
    if f.get("max_contactless_object_path") is not None:
        reach = fit_metaworld_contact_reach(trajs)
        limits["max_contactless_object_path"] = physics_limit(
            f.max_contactless_object_path, metaworld_contactless_object_path(trajs, reach),
            field="flow.max_contactless_object_path")
        checks.append(metaworld_contact_check(reach, limits["max_contactless_object_path"]))
    if f.get("max_hand_step") is not None:
        limits["max_hand_step"] = physics_limit(f.max_hand_step, metaworld_max_hand_step(trajs),
                                                field="flow.max_hand_step")
        checks.append(metaworld_hand_step_check(limits["max_hand_step"]))
    if f.get("max_hand_penetration") is not None:
        limits["max_hand_penetration"] = physics_limit(f.max_hand_penetration, torch.zeros(0),
                                                       field="flow.max_hand_penetration")
        closest = float(metaworld_closest_approach(trajs).min())
        limits["closest_approach"] = closest  # the data's, the penetration's reference
        checks.append(metaworld_penetration_check(closest, limits["max_hand_penetration"]))
    if not checks:
        return None, limits
    return (lambda samples: torch.stack([check(samples) for check in checks]).all(0)), limits


def metaworld_validity(generated: TensorDictBase, data: TensorDictBase) -> dict[str, float]:
    """Validity of the flow's accepted Meta-World samples (paper §4.3 scores it with an oracle
    dynamics model; Meta-World has none): the mean of the three physics proxies over the samples,
    beside the dataset's own as the reference (metres; hand model and reach fitted on the dataset),
    the largest one-step hand move of any sample beside the dataset's largest, the closest hand-object
    approach of any sample beside the dataset's, and the share of samples whose hand comes closer to the object
    than the dataset's ever does (``flow.max_hand_penetration=0`` would reject them) with their mean depth."""
    hand_w = fit_metaworld_hand_model(data)
    try:
        reach = fit_metaworld_contact_reach(data)
    except ValueError:  # a dataset whose object never moves has no reach: report NaN, do not fail the run
        reach = None
    out = {}
    for name, td in (("generated", generated), ("dataset", data)):
        errors = metaworld_physics_errors(td, hand_weights=hand_w, reach=reach)
        for proxy in METAWORLD_PHYSICS_PROXIES:
            out[f"{proxy}_{name}"] = float(errors[proxy].mean()) if proxy in errors else float("nan")
        out[f"max_hand_step_{name}"] = float(metaworld_max_hand_step(td).max()) if td.batch_size[0] else float("nan")
        out[f"closest_approach_{name}"] = (float(metaworld_closest_approach(td).min()) if td.batch_size[0]
                                           else float("nan"))
    depth = metaworld_hand_penetration(generated, out["closest_approach_dataset"])
    out["hand_penetration_share_generated"] = float((depth > 0).float().mean()) if depth.numel() else float("nan")
    out["hand_penetration_depth_generated"] = (float("nan") if not depth.numel() else
                                               float(depth[depth > 0].mean()) if bool((depth > 0).any()) else 0.0)
    return out


def oracle_validity(generated: TensorDictBase, data: TensorDictBase,
                    oracle: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], *, reference_steps: int = 0,
                    seed: int = 0) -> tuple[dict[str, float], torch.Tensor | None]:
    """Validity of the flow's accepted samples as paper §4.3 scores it, on envs with a one-step oracle
    (toy, locomotion; :func:`~torchrl_ftb.envs.dynamics_oracle`): the mean error of their transitions
    against the env's own dynamics, per observation dimension, beside the dataset's (~0) and, with
    ``reference_steps > 0``, beside the paper's reference scale: an MLP one-step model fitted on the dataset, scored
    on held-out trajectories (:func:`torchrl_ftb.analysis.fit_dynamics_reference`). Returns the summary and the
    samples' error by step within the trajectory (``[H]``, None without samples; Fig. 4 right)."""
    err = dynamics_error(generated, oracle) if generated.batch_size[0] else None
    out = {"dynamics_error_generated": err["mean"] if err is not None else float("nan"),
           "dynamics_error_dataset": dynamics_error(data, oracle)["mean"]}
    curve = per_step_mean(err["per_step"], err["valid"]) if err is not None else None
    if reference_steps > 0:
        out["dynamics_error_mlp_heldout"] = fit_dynamics_reference(data, steps=reference_steps, seed=seed)["heldout_error"]
    return out, curve


def validity_reference_steps(cfg: DictConfig) -> int:
    """``analysis.validity_reference_steps``: Adam steps of the MLP dynamics model of :func:`oracle_validity` (0: none;
    default 2000, as in the config)."""
    steps = int(cfg.get("analysis", {}).get("validity_reference_steps", 2000))
    if steps < 0:
        raise ValueError(f"analysis.validity_reference_steps={steps}: must be >= 0 (0: no reference model)")
    return steps


def flow_filter(cfg: DictConfig) -> str:
    """``flow.filter``: ``score_model`` (FTB: s_psi) or ``true_return`` (an oracle bound, not PbRL)."""
    value = str(cfg.flow.get("filter", "score_model"))
    if value not in FLOW_FILTERS:
        raise ValueError(f"flow.filter={value!r}: choose one of {list(FLOW_FILTERS)}")
    return value


def flow_options(cfg: DictConfig) -> dict[str, Any]:
    """``FlowToBetter``'s scalar options from ``cfg.flow`` (and ``blocks.num_blocks``): checked at start
    (:func:`check_flow_options`), before any training, and passed to the flow stage."""
    f = cfg.flow
    return {"top_k": int(f.top_k), "threshold": float(f.threshold), "num_blocks": int(cfg.blocks.num_blocks),
            "flow_steps": _optional_int(f.flow_steps), "max_flow_steps": _optional_int(f.max_flow_steps),
            "min_flow_steps": int(f.min_flow_steps), "early_stop_fraction": float(f.early_stop_fraction),
            "max_abs_z": float(f.max_abs_z), "action_tolerance": float(f.action_tolerance),
            "min_length": _optional_int(f.min_length), "batch_size": int(f.batch_size),
            "candidates": int(f.get("candidates", 1)), "ensemble_rule": str(f.get("ensemble_rule", "mean"))}


def check_policy_options(cfg: DictConfig) -> None:
    """BC's and the evaluation's numbers, checked at start (they are used after the diffuser's training) by the
    library's own checks (:func:`check_policy_sections`)."""
    check_policy_sections({"bc": cfg.bc, "eval": cfg.eval})


def stage_flow(cfg, run: RunDir, trajs, scores, block_ids, sampler, model, true_reward_fn, logger) -> dict:
    path = run.ckpt / "flow.pt"
    if run.done("flow"):
        ckpt = _load_ckpt(path, "torchrl_ftb.flow")
        out = {k: _td_from_ckpt(ckpt, path, k) for k in ("trajectories", "original", "generated")}
        keys = ("stats", "summary", "scores", "original_scores", "source_step", "original_indices", "true_returns",
                "original_true_returns", "filled_true_returns", "original_filled_true_returns")  # indices: None before s29
        return {**out, **{k: ckpt.get(k) for k in keys}}
    f, seed = cfg.flow, stage_seed(cfg, "flow")
    validity_fn, limits = physical_validity_fn(f, trajs)
    if flow_filter(cfg) == "true_return":  # the oracle filter: top-k, acceptance, final ranking by true return
        model = true_return_score(true_reward_fn, horizon=_optional_int(f.get("true_return_horizon")),
                                  streak=_optional_int(f.get("true_return_streak")))
        scores = block_ids = None  # the flow ranks and blocks the dataset by the oracle itself
    flow = FlowToBetter(
        sampler, model, **flow_options(cfg), true_reward_fn=true_reward_fn, seed=seed,
        true_return_horizon=None if true_reward_fn is None or f.get("true_return_horizon") is None
        else int(f.true_return_horizon),
        true_return_streak=None if true_reward_fn is None or f.get("true_return_streak") is None
        else int(f.true_return_streak),
        logger=logger, validity_fn=validity_fn,
        progress=bool(cfg.progress),
    )
    res = flow(trajs, scores=scores, block_ids=block_ids)
    res.summary.update({f"{k}_m": v for k, v in limits.items()})  # the physics limits the flow applied
    res.summary["seed"] = seed
    ckpt = {"kind": "torchrl_ftb.flow", "trajectories": _td_to_ckpt(res.trajectories),
            "original": _td_to_ckpt(res.original), "generated": _td_to_ckpt(res.generated),
            "scores": res.scores, "original_scores": res.original_scores, "source_step": res.source_step,
            "original_indices": res.original_indices, "stats": res.stats, "summary": res.summary, "true_returns": res.true_returns,
            "original_true_returns": res.original_true_returns, "filled_true_returns": res.filled_true_returns,
            "original_filled_true_returns": res.original_filled_true_returns}
    atomic_torch_save(ckpt, path)
    run.mark("flow", **res.summary)
    return {k: v for k, v in ckpt.items() if k != "kind"} | {
        "trajectories": res.trajectories, "original": res.original, "generated": res.generated}


def _tracker_count(cfg: DictConfig | dict, key: str, default: int) -> int:
    """``tracker.<key>`` as an int >= 1 (``default`` when absent); a clear error naming the option otherwise."""
    n = int((cfg.get("tracker") or {}).get(key, default))
    if n < 1:
        raise ValueError(f"tracker.{key}={n}: must be >= 1")
    return n


def tracker_steps(cfg: DictConfig | dict) -> int:
    """``tracker.steps``: Adam steps fitting the run's path tracker (>= 1; default 4000)."""
    return _tracker_count(cfg, "steps", 4000)


def tracker_lookahead(cfg: DictConfig) -> int:
    """``tracker.lookahead``: steps the shooting trackers of ``analysis.tracked`` score each candidate action over
    (>= 1; default 1, greedy): locomotion's (:func:`torchrl_ftb.envs.track_locomotion_paths`) and Meta-World's with
    ``tracker.candidates`` > 1 (:class:`torchrl_ftb.envs.MetaWorldShootingController`)."""
    return _tracker_count(cfg, "lookahead", 1)


def tracker_candidates(cfg: DictConfig) -> int:
    """``tracker.candidates``: actions the Meta-World ``analysis.tracked`` reading tries per step (>= 1; default 4:
    shooting in the simulator, :func:`torchrl_ftb.analysis.track_paths`, exact on recorded paths; 1: the
    inverse-dynamics tracker alone, whose own error moved drawer-open's top-k max by +-100, BENCHMARKS #5 session 48)."""
    return _tracker_count(cfg, "candidates", 4)


def tracker_readers(cfg: DictConfig) -> int:
    """``tracker.readers``: how many times the Meta-World shooting reading (``tracker.candidates`` > 1) reads each
    generated path, each with other perturbations; the path's numbers are the means (>= 1; null, the default: 4
    with shooting, 1 with the tracker alone, :func:`torchrl_ftb.analysis.check_readers`). More than 1 needs
    shooting."""
    value = (cfg.get("tracker") or {}).get("readers")
    n = None if value is None else _tracker_count(cfg, "readers", 1)
    candidates = tracker_candidates(cfg)  # its own error first
    try:
        return check_readers(n, candidates)
    except ValueError as err:
        raise ValueError(f"tracker.readers={n}: {err}; set tracker.candidates") from None


def path_tracker(cfg: DictConfig, run: RunDir, trajs: TensorDictBase, *, progress: bool) -> PathTracker:
    """The goal-conditioned inverse-dynamics tracker that ``bc.relabel_actions`` and ``analysis.tracked`` share
    (:func:`torchrl_ftb.policy.fit_path_tracker` on the dataset, ``tracker.steps`` Adam steps, seeded by
    ``seed``). Fitted once per run: saved to ``checkpoints/tracker.pt`` and reused while its steps and seed
    match (a run whose config changed them refits it)."""
    steps = tracker_steps(cfg)
    path, key = run.path / "checkpoints" / "tracker.pt", {"steps": steps, "seed": int(cfg.seed)}
    if path.is_file():
        ckpt = _load_ckpt(path, "torchrl_ftb.path_tracker")
        if {k: ckpt.get(k) for k in key} == key:
            state = ckpt.get("state_dict") or {}
            tracker = PathTracker(int(trajs["observation"].shape[-1]), int(trajs["action"].shape[-1]),
                                  hidden=int(ckpt.get("hidden", 0)), dims=tuple(ckpt.get("dims", ())))
            try:
                tracker.load_state_dict(state)
            except RuntimeError as err:
                raise ValueError(f"{path}: the tracker does not fit this dataset ({err}); delete the file to refit")
            return tracker
    tracker = fit_path_tracker(trajs, steps=steps, seed=int(cfg.seed), progress=progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_torch_save({"kind": "torchrl_ftb.path_tracker", **key, "hidden": int(tracker.net[0].out_features),
                       "dims": list(tracker.dims), "state_dict": tracker.state_dict()}, path)
    return tracker


def relabel_generated(cfg, run: RunDir, improved: TensorDictBase, generated: torch.Tensor,
                      trajs: TensorDictBase) -> TensorDictBase:
    """``bc.relabel_actions``: the final set with its generated trajectories' actions replaced by those the
    run's tracker (:func:`path_tracker`) gives for their own states
    (:meth:`torchrl_ftb.policy.PathTracker.relabel`). Off (the paper's): the diffuser's own actions."""
    if not switch(cfg, "bc.relabel_actions") or not bool(torch.as_tensor(generated).any()):
        return improved
    tracker = path_tracker(cfg, run, trajs, progress=bool(cfg.progress))
    return tracker.relabel(improved, torch.as_tensor(generated).bool().cpu())


def bc_trajectories(cfg: DictConfig, flow: dict) -> tuple[TensorDictBase, torch.Tensor]:
    """What BC clones, and which of it is generated (``[N]`` bool): the flow's final set (the paper), or with
    ``bc.keep_top_k`` the original top-k plus the final set's generated trajectories (the flow's samples as an
    augmentation of the data it started from, which then stays in)."""
    keys = ("observation", "action", "mask")
    final, generated = flow["trajectories"].select(*keys), torch.as_tensor(flow["source_step"]).cpu() > 0
    if not switch(cfg, "bc.keep_top_k"):
        return final, generated
    original = flow["original"].select(*keys)
    kept = torch.cat([original, final[generated]], 0)
    return kept, torch.arange(kept.batch_size[0]) >= original.batch_size[0]


def stage_seed(cfg: DictConfig, stage: str) -> int:
    """The seed of one stage's own randomness: ``<stage>.seed``, or the run's ``seed`` when null, so the stage can
    be repeated on the same earlier stages (``redo_from=<stage>``) to measure its own spread. ``bc``: the actor's
    initialisation and batches; ``flow``: the sampler's noise and the flow's draws."""
    value = cfg[stage].get("seed")
    if value is None:
        return int(cfg.seed)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{stage}.seed={value!r}: must be a whole number >= 0, or null (the run's seed)")
    return value


def stage_bc(cfg, run: RunDir, improved, device, logger):
    b = cfg.bc
    seed = stage_seed(cfg, "bc")
    flat = trajectories_to_flat(improved.select("observation", "action", "mask"))
    torch.manual_seed(seed)
    actor = make_bc_actor_for(flat, hidden=tuple(b.hidden), device=device)
    path = run.ckpt / "bc.pt"
    if run.done("bc"):
        load_bc_checkpoint(path, actor)
        return actor, run.stages["bc"]
    buffer = make_transition_buffer(flat, batch_size=int(b.batch_size), seed=seed)
    out = train_bc(
        actor, buffer, steps=int(b.steps), batch_size=int(b.batch_size), lr=float(b.lr),
        weight_decay=float(b.weight_decay), seed=seed, logger=logger, progress=bool(cfg.progress),
        device=device, checkpoint_path=path, checkpoint_every=int(b.checkpoint_every), resume=run.resume,
    )
    summary = {"steps": out["steps"], "resumed_from": out["start_step"], "final_loss": out["loss"],
               "num_transitions": int(flat.numel()), "seed": seed}
    run.mark("bc", **summary)
    return actor, summary


def open_loop_analysis(cfg: DictConfig, run: RunDir, flow: dict, trajs: TensorDictBase, meta: dict, *,
                       progress: bool) -> dict | None:
    """``analysis.open_loop``: the flow's improvement in the simulator (generated Meta-World data and locomotion,
    else None).

    Replays the final set's generated trajectories open loop: on Meta-World from their nearest dataset start
    (:func:`torchrl_ftb.analysis.open_loop_improvement`), on locomotion every trajectory from the state of its own
    first observation (:func:`torchrl_ftb.analysis.locomotion_open_loop_improvement`). Writes the per-sample
    numbers to ``open_loop.json`` and a claimed-vs-replayed scatter to ``plots/``, and returns the summary.
    """
    if not bool(cfg.get("analysis", {}).get("open_loop", False)):
        return None
    source = torch.as_tensor(flow["source_step"]) > 0
    if env_kind(cfg.env.name) == "locomotion":
        out = locomotion_open_loop_improvement(flow["trajectories"], flow["original"], source,
                                               env_name=str(cfg.env.name), progress=progress)
        column, horizon_text, highlight, highlight_label = "plain", "", "replay_terminated", "the env ends the replay early"
    elif meta.get("domain") == "metaworld" and "per_trajectory" in meta:
        horizon = _optional_int(cfg.flow.get("true_return_horizon")) or int(cfg.env.max_episode_steps)
        out = open_loop_improvement(flow["trajectories"], flow["original"], source, trajs, meta,
                                    task=str(cfg.env.name), horizon=horizon,
                                    original_rows=flow.get("original_indices"), progress=progress)
        column, horizon_text = "stop_rule", f" (stop rule, {horizon} steps)"
        highlight, highlight_label = "replay_success", "replay succeeds"
    else:
        return None  # no goals and starts to replay from (toy, D4RL/Minari Meta-World files)
    samples = out.pop("samples")
    write_json(run.path / "open_loop.json", {**out, "samples": samples})
    if samples:
        plot_scatter([s[f"claimed_{column}"] for s in samples], [s[f"replayed_{column}"] for s in samples],
                     run.path / "plots" / "open_loop_claimed_vs_replayed.png",
                     xlabel=f"return read off the generated states{horizon_text}",
                     ylabel="return of the actions replayed in the simulator",
                     highlight=[s[highlight] for s in samples], highlight_label=highlight_label,
                     title=f"generated trajectories in the final set — {cfg.env.name}")
    return out


def tracked_analysis(cfg: DictConfig, run: RunDir, flow: dict, trajs: TensorDictBase, meta: dict, *,
                     progress: bool) -> dict | None:
    """``analysis.tracked``: the flow's improvement with every state path tracked in closed loop (generated
    Meta-World data and locomotion, else None; off by default).

    Meta-World: tracks the original top-k and the final set's generated trajectories in the simulator
    (:func:`torchrl_ftb.analysis.tracked_improvement`): by default shooting (``tracker.candidates`` 4: the path's own
    action, the run's inverse-dynamics tracker's, :func:`path_tracker`, and perturbations), each generated path read
    ``tracker.readers`` times (null: 4); ``tracker.candidates=1``: the inverse-dynamics tracker alone.
    Locomotion: a shooting tracker with the simulator as its model (``tracker.lookahead``) follows every path of
    both sets from its own first state (:func:`torchrl_ftb.analysis.locomotion_tracked_improvement`). Writes the per-sample
    numbers to ``tracked.json`` and returns the summary.
    """
    analysis = cfg.get("analysis", {})
    if not bool(analysis.get("tracked", False)):
        return None
    source = torch.as_tensor(flow["source_step"]) > 0
    if env_kind(cfg.env.name) == "locomotion":  # the simulator as the tracker's model, from each path's own start
        out = locomotion_tracked_improvement(flow["trajectories"], flow["original"], source,
                                             env_name=str(cfg.env.name), lookahead=tracker_lookahead(cfg),
                                             seed=int(cfg.seed), progress=progress)
        extra = {}
    elif meta.get("domain") == "metaworld" and "per_trajectory" in meta:
        horizon = _optional_int(cfg.flow.get("true_return_horizon")) or int(cfg.env.max_episode_steps)
        tracker = path_tracker(cfg, run, trajs, progress=progress)
        out = tracked_improvement(flow["trajectories"], flow["original"], source, trajs, meta,
                                  task=str(cfg.env.name), horizon=horizon, tracker=tracker,
                                  original_rows=flow.get("original_indices"), candidates=tracker_candidates(cfg),
                                  lookahead=tracker_lookahead(cfg), readers=tracker_readers(cfg), progress=progress)
        extra = {"tracker_steps": tracker_steps(cfg)}
    else:
        return None  # no goals and starts to track from (toy, D4RL/Minari Meta-World files)
    samples = out.pop("samples")
    write_json(run.path / "tracked.json", {**out, **extra, "samples": samples})
    return out


# ====================================================================
# Reporting
# ---------


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _mean_max(summary: dict) -> str:
    """``"mean before -> after / max before -> after"`` of a ``return_summary``."""
    return (f"{summary['true_return_mean_before']:.4g} -> {summary['true_return_mean_after']:.4g} / "
            f"{summary['true_return_max_before']:.4g} -> {summary['true_return_max_after']:.4g}")


def open_loop_rows(ol: dict | None) -> list[tuple[str, str]]:
    """The report rows of ``analysis.open_loop`` (Meta-World: stop-rule returns from the nearest dataset start;
    locomotion, ``horizon`` None: plain returns, each trajectory from its own first state)."""
    if ol is None:
        return []
    locomotion = ol.get("horizon") is None
    key = "plain" if locomotion else f"stop_rule_{int(ol['horizon'])}"
    rows = [(("true return top-k replayed open loop in the simulator" if locomotion else
              f"true return top-k replayed in the simulator (stop rule, {int(ol['horizon'])} steps)")
             + ": mean / max before -> after", _mean_max(ol["improvement"][key]["replayed"]))]
    if locomotion:  # the simulator's fidelity: HalfCheetah's contacts amplify the float32 rounding of a state
        recorded = ol["improvement"][key]["claimed"]["true_return_mean_before"]
        replayed = ol["improvement"][key]["replayed"]["true_return_mean_before"]
        rows.append(("simulator on the top-k's own actions: recorded -> replayed mean (equal: the data reproduced)",
                     f"{recorded:.4g} -> {replayed:.4g}"))
    if not ol["num_generated"]:
        return rows
    if locomotion:
        rows.append(("generated in final set, replayed: return claimed -> replayed (replays the env ends "
                     "early; median share of steps run)",
                     f"{ol['claimed_plain_mean_generated']:.4g} -> {ol['replayed_plain_mean_generated']:.4g} "
                     f"({_fmt(ol['replay_terminated_rate'])}; {_fmt(ol['replay_length_fraction_median'])})"))
        return rows
    rows.append(("generated in final set, replayed: return claimed -> replayed (replays that succeed)",
                 f"{ol['claimed_stop_rule_mean_generated']:.4g} -> "
                 f"{ol['replayed_stop_rule_mean_generated']:.4g} ({_fmt(ol['replay_success_rate'])})"))
    rows.append(("generated in final set, first step: off the nearest dataset start, m (median) / "
                 "hand-object distance, m: sample vs that start",
                 f"{_fmt(ol['start_distance_median'])} / {_fmt(ol['start_hand_object_median'])} vs "
                 f"{_fmt(ol['data_start_hand_object_median'])}"))
    return rows


def tracked_rows(tr: dict | None) -> list[tuple[str, str]]:
    """The report rows of ``analysis.tracked`` (Meta-World: shooting or the inverse-dynamics tracker, stop-rule returns;
    locomotion, ``horizon`` None: the simulator shooting tracker, plain returns)."""
    if tr is None:
        return []
    fid, gen = tr["fidelity"], tr["generated"]
    locomotion = tr.get("horizon") is None
    lookahead = int(tr.get("lookahead") or 1)  # runs before session 35 did not record it: greedy
    shooting = "simulator shooting tracker" + (f", {lookahead}-step lookahead" if lookahead > 1 else "")
    shot = tr.get("shooting") or {}  # Meta-World; runs before session 47 did not record it: the tracker alone
    if int(shot.get("candidates", 1)) > 1:
        look, readers = int(shot.get("lookahead", 1)), int(shot.get("readers", 1))
        shot_text = (f"; shooting, {int(shot['candidates'])} candidates"
                     + (f", {look}-step lookahead" if look > 1 else "")
                     + (f", generated paths: mean of {readers} readings" if readers > 1 else ""))
    else:
        shot_text = ""
    rows = [((f"true return top-k tracked in closed loop ({shooting})" if locomotion else
              f"true return top-k tracked in closed loop (stop rule, {int(tr['horizon'])} steps{shot_text})")
             + ": mean / max before -> after", _mean_max(tr["tracked"]))]
    if locomotion:
        rows.append(("tracker on the top-k: claimed -> tracked mean (scaled path error, median)",
                     f"{fid['claimed_mean']:.4g} -> {fid['tracked_mean']:.4g} ({_fmt(fid['path_error_median'])})"))
        if gen["num_generated"]:
            rows.append(("generated in final set, tracked: return claimed -> tracked (tracks the env ends early; "
                         "scaled path error, median)",
                         f"{gen['claimed_plain_mean']:.4g} -> {gen['tracked_plain_mean']:.4g} "
                         f"({_fmt(gen['tracked_terminated_rate'])}; {_fmt(gen['path_error_median'])})"))
        return rows
    rows.append(("tracker on the top-k: recorded -> tracked mean (hand off its path, m, median)",
                 f"{fid['recorded_mean']:.4g} -> {fid['tracked_mean']:.4g} ({_fmt(fid['hand_deviation_median'])})"))
    if gen.get("off_path"):  # runs before session 32 did not record it
        rows.append((f"the same without the {gen['off_path']} generated paths the tracker left further than any "
                     "top-k path: mean / max before -> after", _mean_max(tr["tracked_on_path"])))
    if gen["num_generated"]:
        rows.append(("generated in final set, tracked: return claimed -> tracked (hand off its path, m, median)",
                     f"{gen['claimed_stop_rule_mean']:.4g} -> {gen['tracked_stop_rule_mean']:.4g} "
                     f"({_fmt(gen['hand_deviation_median'])})"))
    return rows


def final_table(metrics: dict) -> list[tuple[str, str]]:
    ev, fl = metrics["eval"], metrics["flow"]
    rows = [("env", metrics["env"]), ("preset", metrics["preset"]), ("teacher", metrics["teacher"])]
    oracle = metrics.get("flow_filter", "score_model") == "true_return"
    if oracle:
        rows.append(("flow filter", "true return (oracle bound: not preference-based)"))
    if "success_rate" in ev:
        rows.append(("success rate (FTB policy)", _fmt(ev["success_rate"])))
    if "normalized_score" in ev:
        rows.append(("D4RL normalized score (FTB policy)",
                     f"{ev['normalized_score']:.4g} ± {ev['normalized_score_std']:.3g}"))
    rows += [
        ("return (FTB policy)", f"{ev['return_mean']:.4g} ± {ev['return_std']:.3g}"),
        ("episode length", _fmt(ev["length_mean"])),
        (f"{'filter score (true return)' if oracle else 'score s_psi'} top-k: before -> after",
         f"{fl['score_mean_before']:.4g} -> {fl['score_mean_after']:.4g}"),
    ]
    if "true_return_mean_before" in fl:
        rows.append(("true return top-k: before -> after",
                     f"{fl['true_return_mean_before']:.4g} -> {fl['true_return_mean_after']:.4g}"))
    if "true_return_filled_mean_before" in fl:
        rows.append((f"true return, stop-rule fill to {int(fl['true_return_horizon'])} steps: before -> after",
                     f"{fl['true_return_filled_mean_before']:.4g} -> {fl['true_return_filled_mean_after']:.4g}"))
    if "true_return_filled_stop_rule_mean_before" in fl:
        rows.append((f"the same after the stop-rule cut ({int(fl['true_return_streak'])} successes): before -> after",
                     f"{fl['true_return_filled_stop_rule_mean_before']:.4g} -> "
                     f"{fl['true_return_filled_stop_rule_mean_after']:.4g}"))
    rows += open_loop_rows(metrics.get("analysis", {}).get("open_loop"))
    rows += tracked_rows(metrics.get("analysis", {}).get("tracked"))
    rows += [
        ("flow steps run / planned", f"{int(fl['flow_steps_run'])} / {int(fl['flow_steps_planned'])}"),
        ("generated trajectories in final set", _fmt(fl["fraction_generated_in_final"])),
        ("score Spearman vs true return", _fmt(metrics["score_quality"].get("spearman_return", float("nan")))),
    ]
    v = metrics.get("analysis", {}).get("validity", {})
    if "dynamics_error_generated" in v:
        rows.append(("accepted samples: one-step dynamics error per observation dim (dataset)",
                     f"{_fmt(v['dynamics_error_generated'])} ({_fmt(v['dynamics_error_dataset'])})"))
        if "dynamics_error_mlp_heldout" in v:
            rows.append(("the same of an MLP one-step model on held-out real transitions (the paper's reference)",
                         _fmt(v["dynamics_error_mlp_heldout"])))
    if "frame_stack_error_generated" in v:
        rows.append(("accepted samples: frame-stack / hand-model error / contactless object path, m (dataset)",
                     " / ".join(f"{_fmt(v[f'{k}_generated'])} ({_fmt(v[f'{k}_dataset'])})"
                                for k in METAWORLD_PHYSICS_PROXIES)))
        if "max_hand_step_generated" in v:  # runs before session 32 did not record it
            rows.append(("accepted samples: largest one-step hand move, m (dataset)",
                         f"{_fmt(v['max_hand_step_generated'])} ({_fmt(v['max_hand_step_dataset'])})"))
        if "closest_approach_generated" in v:  # runs before session 53 did not record it
            rows.append(("accepted samples: closest hand-object approach, m (dataset); share closer than the "
                         "dataset's hand ever comes, mean depth, m",
                         f"{_fmt(v['closest_approach_generated'])} ({_fmt(v['closest_approach_dataset'])}); "
                         f"{_fmt(v['hand_penetration_share_generated'])}, "
                         f"{_fmt(v['hand_penetration_depth_generated'])}"))
    if "top_k_success" in metrics["score_quality"]:
        sq = metrics["score_quality"]
        if oracle and "top_k_success" in fl:  # the flow started from the oracle's top-k, not s_psi's
            rows.append(("successes in the filter's top-k / s_psi's (dataset share)",
                         f"{_fmt(fl['top_k_success'])} / {_fmt(sq['top_k_success'])} ({_fmt(sq['dataset_success'])})"))
        else:
            rows.append(("successes in the top-k (dataset share)",
                         f"{_fmt(sq['top_k_success'])} ({_fmt(sq['dataset_success'])})"))
    rows += [
        ("wall time (s)", _fmt(metrics["wall_time_s"])),
    ]
    return rows


def write_report(run: RunDir, metrics: dict, flow_stats: list[dict]) -> Path:
    lines = [f"# FTB offline — {metrics['env']} ({metrics['preset']} preset, teacher {metrics['teacher']})", "",
             "| metric | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in final_table(metrics)]
    if "true_return_mean_before" in metrics["flow"]:
        lines += ["", "The flow's true returns of generated trajectories are the ground-truth reward read off their "
                  "generated states, not what executing their actions achieves. On generated Meta-World data the "
                  "\"replayed in the simulator\" rows are the simulator's own: recorded rewards for dataset "
                  "trajectories, open-loop replays of the generated ones' actions from their nearest dataset start "
                  "(`analysis.open_loop`, per-sample numbers in `open_loop.json`; BENCHMARKS.md, session 29: there "
                  "the flow's gains vanish). On locomotion every trajectory of both sets is replayed open loop from "
                  "the state of its own first observation until its actions run out or the env ends it."]
    lines += ["", "## Flow steps", ""]
    if flow_stats:
        keys = list(flow_stats[0].keys())
        lines += ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
        lines += ["| " + " | ".join(_fmt(r.get(k)) for k in keys) + " |" for r in flow_stats]
    else:
        lines.append("No flow step was run.")
    lines += ["", "## Stages", ""]
    for name in STAGES:
        summary = {k: v for k, v in run.stages.get(name, {}).items() if k != "done"}
        lines.append(f"- **{name}**: " + ", ".join(f"{k}={_fmt(v)}" for k, v in summary.items()))
    lines += ["", "## Plots", ""] + [f"![{p.stem}](plots/{p.name})" for p in sorted((run.path / "plots").glob("*.png"))]
    lines += ["", f"git commit: `{metrics.get('git_commit')}`", ""]
    path = run.path / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path


# ====================================================================
# Main
# ----


def run(cfg: DictConfig) -> dict:
    """Run (or resume) the whole FTB pipeline for ``cfg``; returns the metrics dict."""
    if cfg.preset not in cfg.presets:
        raise ValueError(f"preset={cfg.preset!r} is unknown; choose one of {sorted(cfg.presets)}")
    kind = env_kind(cfg.env.name)
    if cfg.labels.teacher not in ("return", "success"):
        raise ValueError(f"labels.teacher={cfg.labels.teacher!r}: choose 'return' or 'success'")
    query = dict(cfg.labels.get("query") or {})
    if query.get("strategy", "random") not in QUERY_STRATEGIES:
        raise ValueError(f"labels.query.strategy={query.get('strategy')!r}: choose one of {list(QUERY_STRATEGIES)}")
    check_physics_limit_specs(cfg.flow)  # a malformed limit fails now, not after the diffuser's training
    for key, what in PHYSICS_LIMIT_KEYS.items():
        if cfg.flow.get(key) is not None and kind != "metaworld":
            raise ValueError(f"flow.{key} is a Meta-World check ({what}); "
                             f"env.name={cfg.env.name!r} is {kind}: leave it null")
    for key in ("score_model.horizon", "flow.true_return_horizon"):
        if OmegaConf.select(cfg, key) is not None and kind == "locomotion":
            raise ValueError(f"{key} is the stop-rule fill for tasks without terminal states (Meta-World); "
                             f"env.name={cfg.env.name!r} episodes terminate (falls) and the diffuser's samples carry "
                             f"no termination flag: leave it null")
    sdedit_strength(cfg)  # a malformed strength fails now, not after the diffuser's training
    score_guidance(cfg)
    score_guidance_kappa(cfg)  # and its members
    pair_neighbours(cfg)
    top_block_pairs(cfg)
    switch(cfg, "bc.keep_top_k")  # a malformed switch fails now, not after the flow
    stage_seed(cfg, "bc")
    stage_seed(cfg, "flow")
    try:  # the flow's numbers fail now, not after the diffuser's training
        check_flow_options(**flow_options(cfg), num_members=1 if flow_filter(cfg) == "true_return"
                           else int(cfg.score_model.get("num_members", 1)))
    except (ValueError, TypeError) as err:  # TypeError: e.g. flow.top_k=null
        raise ValueError(f"flow.* (or blocks.num_blocks): {err}") from None
    for key in ("flow.true_return_horizon", "flow.true_return_streak"):  # read by the flow stage only
        value = OmegaConf.select(cfg, key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{key}={value!r}: must be a whole number >= 1, or null")
    check_policy_options(cfg)
    inpaint_start(cfg)
    tracker_steps(cfg)
    tracker_lookahead(cfg)
    tracker_candidates(cfg)
    tracker_readers(cfg)
    validity_reference_steps(cfg)
    if flow_filter(cfg) == "true_return" and not cfg.flow.true_reward:
        raise ValueError("flow.filter=true_return ranks and accepts by the ground-truth return: it needs "
                         "flow.true_reward=true")
    if cfg.flow.get("true_return_streak") is not None:
        if kind != "metaworld":
            raise ValueError(f"flow.true_return_streak is the Meta-World stop rule's cut; env.name={cfg.env.name!r} "
                             f"is {kind}: leave it null")
        if cfg.flow.get("true_return_horizon") is None:
            raise ValueError("flow.true_return_streak needs flow.true_return_horizon (the cut applies to that fill)")
    stop_after = cfg.get("stop_after")
    if stop_after is not None and stop_after not in STAGES:
        raise ValueError(f"stop_after={stop_after!r}: not a stage; choose one of {list(STAGES)}")
    t_start = time.perf_counter()
    torch.manual_seed(int(cfg.seed))
    device = torch.device(cfg.device)
    run_dir = RunDir(cfg)
    print(f"run dir: {run_dir.path}  (continue a killed run with resume=true run_dir={run_dir.path})")
    logger = make_logger(cfg.logger.backend, log_dir=run_dir.path / "logs",
                         experiment_name=f"ftb_{cfg.env.name}_seed{cfg.seed}", project=cfg.logger.project_name,
                         mode=cfg.logger.mode, config=OmegaConf.to_container(cfg, resolve=True))
    progress = bool(cfg.progress)
    timings: dict[str, float] = {}

    def timed(name: str, t0: float) -> None:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0

    partial_metrics: dict[str, Any] = {}  # what the finished stages reported so far

    def stopped(stage: str) -> dict | None:
        """With ``stop_after=stage``: the partial metrics (``metrics_partial.json``), else None."""
        if stage != stop_after:
            return None
        partial = {"env": cfg.env.name, "preset": cfg.preset, "teacher": str(cfg.labels.teacher),
                   "seed": int(cfg.seed), "stopped_after": stage, **partial_metrics, "stage_time_s": timings,
                   "wall_time_s": time.perf_counter() - t_start, "git_commit": git_commit(),
                   "machine": machine_info(), "command": " ".join(sys.argv), "run_dir": str(run_dir.path)}
        write_json(run_dir.path / "metrics_partial.json", partial)
        print(f"stopped after {stage} (stop_after); continue with resume=true run_dir={run_dir.path}")
        return partial

    # 1. dataset ------------------------------------------------------------------------
    t0 = time.perf_counter()
    # envs and data: torchrl_ftb.datasets.make_dataset (cached) / torchrl_ftb.envs.make_env
    name, limit = cfg.env.name, int(cfg.env.max_episode_steps)
    trajs, meta = make_dataset(name, **dataset_kwargs(name, cfg.dataset, max_episode_steps=limit,
                                                      progress=progress))
    eval_env = functools.partial(make_env, name, seed=int(cfg.eval.seed), toy_horizon=int(cfg.dataset.horizon),
                                 max_episode_steps=None if kind == "locomotion" else limit)  # locomotion: 1000
    obs_dim, act_dim = check_env_matches(eval_env, trajs, name=name)
    if not run_dir.done("dataset"):
        run_dir.mark("dataset", num_trajectories=int(trajs.batch_size[0]), horizon=int(trajs.batch_size[1]),
                     obs_dim=obs_dim, action_dim=act_dim, path=meta.get("path"))
    else:  # the run's dataset: the same size and, where recorded, the same cache entry (its key names the data)
        recorded = run_dir.stages["dataset"]
        if recorded.get("num_trajectories") != int(trajs.batch_size[0]) or \
                recorded.get("path") not in (None, meta.get("path")):
            raise ValueError(f"{run_dir.stages_file}: the dataset changed since the run started "
                             f"({recorded.get('num_trajectories')} trajectories at {recorded.get('path')}, now "
                             f"{int(trajs.batch_size[0])} at {meta.get('path')}); start a new run_dir")
    if int(cfg.flow.top_k) > trajs.batch_size[0]:  # fails now, not at the flow stage
        raise ValueError(f"flow.top_k={cfg.flow.top_k} exceeds the dataset's {trajs.batch_size[0]} trajectories")
    timed("dataset", t0)
    if (out := stopped("dataset")) is not None:
        return out

    # 2. labels -------------------------------------------------------------------------
    t0 = time.perf_counter()
    teacher = make_teacher(str(cfg.labels.teacher), discount=float(cfg.labels.discount),
                           horizon=_optional_int(cfg.labels.get("horizon")))
    label_dir = run_dir.ckpt / "labels"
    if run_dir.done("labels"):
        labels, _ = load_labels(label_dir)
        check_labels_match(labels, trajs, name=str(label_dir))  # the labelled trajectories are this dataset's
    else:
        sm_cfg = cfg.score_model
        labels = make_query_labels(
            trajs, num_pairs=int(cfg.labels.num_pairs), teacher=teacher, seed=int(cfg.labels.seed), **query,
            model_kwargs={k: sm_cfg.get(k) for k in ("num_cells", "num_layers", "gamma", "reward_activation",
                                                     "horizon")},
            normalize_observations=bool(sm_cfg.get("normalize_observations")), device=device,
        )
        save_labels(labels, label_dir, meta={"teacher": teacher.config(), "query": query})
        run_dir.mark("labels", num_pairs=int(labels.batch_size[0]), teacher=teacher.name,
                     query=query.get("strategy", "random"), ties=int((labels.get("label") == 0.5).sum()))
    timed("labels", t0)
    if (out := stopped("labels")) is not None:
        return out

    # 3. score model, 4. blocks ---------------------------------------------------------
    t0 = time.perf_counter()
    model = stage_score_model(cfg, run_dir, trajs, labels, obs_dim, act_dim, device, logger)
    timed("score_model", t0)
    if (out := stopped("score_model")) is not None:
        return out
    t0 = time.perf_counter()
    scores, block_ids = stage_blocks(cfg, run_dir, trajs, model)
    returns = teacher.returns(trajs)  # the teacher's own definition (discount, stop-rule fill)
    quality = {f"{k}_return": v for k, v in correlations(scores, returns).items()}
    # per-trajectory success (Meta-World, toy), read by the score quality here and the report's top-k row
    succ = SuccessTeacher().succeeded(trajs).float() if ("next", "success") in trajs.keys(True) else None
    if succ is not None:
        quality.update({f"{k}_success": v for k, v in correlations(scores, succ).items()})
        # the successes among the trajectories the flow starts from (BC's data but for accepted samples)
        quality.update(top_k_success=top_k_mean(scores, succ, min(int(cfg.flow.top_k), succ.numel())),
                       dataset_success=float(succ.mean()))
    timed("blocks", t0)
    partial_metrics["score_quality"] = quality
    if (out := stopped("blocks")) is not None:
        return out

    # 5. diffuser -----------------------------------------------------------------------
    t0 = time.perf_counter()
    diffuser, diffuser_summary = stage_diffuser(cfg, run_dir, trajs, scores, block_ids, obs_dim, act_dim, device, logger)
    timed("diffuser", t0)
    partial_metrics["diffuser"] = diffuser_summary
    if (out := stopped("diffuser")) is not None:
        return out

    # 6. flow ---------------------------------------------------------------------------
    t0 = time.perf_counter()
    streak = cfg.flow.get("true_return_streak")
    reward_fn = true_reward_fn(cfg.env.name, with_success=streak is not None) if cfg.flow.true_reward else None
    guide, guide_summary = ((None, {}) if run_dir.done("flow")  # loaded, not sampled
                            else flow_guide(cfg, run_dir, model, scores, trajs, labels, device))
    if guide_summary:  # the guide's own ensemble, timed apart from the flow
        partial_metrics["guide"] = guide_summary
        timed("guide", t0)
        t0 = time.perf_counter()
    flow = stage_flow(cfg, run_dir, trajs, scores, block_ids, make_sampler(cfg, diffuser, guide), model, reward_fn,
                      logger)
    timed("flow", t0)
    partial_metrics.update(flow=dict(flow["summary"]), flow_stats=flow["stats"])
    if (out := stopped("flow")) is not None:
        return out

    # 7. BC -----------------------------------------------------------------------------
    t0 = time.perf_counter()
    improved, generated = bc_trajectories(cfg, flow)
    if not run_dir.done("bc"):
        improved = relabel_generated(cfg, run_dir, improved, generated, trajs)
    actor, bc_summary = stage_bc(cfg, run_dir, improved, device, logger)
    timed("bc", t0)
    partial_metrics["bc"] = bc_summary
    if (out := stopped("bc")) is not None:
        return out

    # 8. evaluation ---------------------------------------------------------------------
    t0 = time.perf_counter()
    ev = evaluate_policy(eval_env, actor, num_episodes=cfg.eval.num_episodes, seed=int(cfg.eval.seed),
                         max_steps=cfg.eval.max_steps, num_envs=cfg.eval.num_envs,
                         stop_on_success=bool(cfg.eval.stop_on_success) and kind == "metaworld",
                         normalized_score_fn=normalized_score_fn(cfg.env.name), progress=progress)
    run_dir.mark("eval", **ev)
    if logger is not None:
        for k, v in ev.items():
            logger.log_scalar(f"eval/{k}", float(v), step=int(cfg.bc.steps))
    timed("eval", t0)

    # analysis, plots, report -------------------------------------------------------------
    plots = run_dir.path / "plots"
    summary = dict(flow["summary"])
    if succ is not None and flow.get("original_indices") is not None:
        # the successes among the trajectories the flow actually started from (the filter's top-k)
        summary["top_k_success"] = float(succ[flow["original_indices"]].mean())
    before = {"score_mean": summary["score_mean_before"], "score_max": summary["score_max_before"]}
    if "true_return_mean_before" in summary:
        before.update(true_return_mean=summary["true_return_mean_before"],
                      true_return_max=summary["true_return_max_before"])
    plot_flow_curves(flow["stats"], plots / "flow_steps.png", before=before, title=f"FTB flow — {cfg.env.name}")
    plot_histograms({"original top-k": flow["original_scores"], "after flow": flow["scores"]},
                    plots / "scores_before_after.png", xlabel="score s_psi")
    analysis: dict[str, Any] = {}
    if flow.get("true_returns") is not None:
        ret0, ret1 = flow["original_true_returns"], flow["true_returns"]
        plot_histograms({"original top-k": ret0, "after flow": ret1}, plots / "true_return_before_after.png",
                        xlabel="true return")
        analysis["improvement"] = {k: v for k, v in summary.items() if k.startswith("true_return_")}
    if flow.get("filled_true_returns") is not None:
        plot_histograms({"original top-k": flow["original_filled_true_returns"], "after flow": flow["filled_true_returns"]},
                        plots / "true_return_filled_before_after.png",
                        xlabel=f"true return, stop-rule fill to {int(summary['true_return_horizon'])} steps")
    if flow["generated"].batch_size[0]:
        nov = novelty(flow["generated"], trajs.select("observation", "action", "mask"), seed=int(cfg.seed))
        analysis["novelty"] = {"generated_mean": nov["generated_mean"], "perturbed_mean": nov["perturbed_mean"]}
        if kind == "metaworld":
            analysis["validity"] = metaworld_validity(flow["generated"], trajs)
        else:
            analysis["validity"], curve = oracle_validity(
                flow["generated"], trajs, dynamics_oracle(cfg.env.name, toy_horizon=int(cfg.dataset.horizon)),
                reference_steps=validity_reference_steps(cfg), seed=int(cfg.seed))
            v = analysis["validity"]
            plot_curves({"accepted samples, against the env's dynamics": curve}, plots / "validity_per_step.png",
                        xlabel="step h within the trajectory", ylabel="|s' - oracle(s, a)|_1 / obs dim", log_y=True,
                        levels={k: v[f"dynamics_error_{key}"] for k, key in
                                (("MLP model on held-out real transitions", "mlp_heldout"),
                                 ("real transitions", "dataset")) if v.get(f"dynamics_error_{key}", 0) > 0},
                        title=f"validity of the flow's samples — {cfg.env.name}")
    t0 = time.perf_counter()
    if (open_loop := open_loop_analysis(cfg, run_dir, flow, trajs, meta, progress=progress)) is not None:
        analysis["open_loop"] = open_loop
        timed("open_loop", t0)
    t0 = time.perf_counter()
    if (tracked := tracked_analysis(cfg, run_dir, flow, trajs, meta, progress=progress)) is not None:
        analysis["tracked"] = tracked
        timed("tracked", t0)

    metrics = {
        "env": cfg.env.name, "preset": cfg.preset, "teacher": teacher.name, "seed": int(cfg.seed),
        "eval": ev, "flow": summary, "flow_filter": flow_filter(cfg), "flow_stats": flow["stats"],
        "score_quality": quality,
        "diffuser": diffuser_summary, "bc": bc_summary, "analysis": analysis,
        **({"guide": partial_metrics["guide"]} if "guide" in partial_metrics else {}),
        "stage_time_s": timings, "wall_time_s": time.perf_counter() - t_start,
        "git_commit": git_commit(), "machine": machine_info(),
        "command": " ".join(sys.argv), "run_dir": str(run_dir.path),
    }
    write_json(run_dir.path / "metrics.json", metrics)
    (run_dir.path / "metrics_partial.json").unlink(missing_ok=True)  # superseded by the whole run's
    write_report(run_dir, metrics, flow["stats"])
    rows = final_table(metrics)
    width = max(len(k) for k, _ in rows)
    print("\n" + "\n".join(f"{k:<{width}}  {v}" for k, v in rows) + f"\nrun dir: {run_dir.path}")
    return metrics


@hydra.main(config_path="config", config_name="ftb_offline", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
