"""Table-1 baselines on FTB's data: one hydra recipe, ``method=`` switch (TorchRL sota style).

    python recipes/baselines.py method=iql env.name=button-press-v3 seed=0
    python recipes/baselines.py method=iql_rpsi labels.teacher=success
    python recipes/baselines.py method=bc10 env.name=toy preset=cpu
    python recipes/baselines.py method=td3bc env.name=hopper +dataset.options.kind=medium-replay
    python recipes/baselines.py method=iql augmentation.kind=ftb env.name=hopper \
        +dataset.options.kind=medium-replay            # FTB as data augmentation (paper §4.4)

Stages: dataset (the generated, cached dataset FTB uses) → scripted labels (same seed →
same pairs) → optionally a supplement of generated trajectories (``augmentation.kind``: ``ftb``
or ``synthetic``, ``torchrl_ftb.augmentation.build_supplement``, cached and resumable under
``augmentation.cache_dir``; on locomotion its actions are replayed open loop, and with ``augmentation.tracked=true``
its paths tracked in closed loop, to read what it is worth executed) merged into the data → the method
(``torchrl_ftb.baselines.run_baseline``) → evaluation with
``torchrl_ftb.policy.evaluate_policy`` (FTB's protocol). The run directory
(``run_dir``, as in recipes/ftb_offline.py) receives ``config.yaml`` (resolved), ``actor.pt`` (state dict,
``torch.load(weights_only=True)``), ``metrics.json``, ``report.md`` and the logger's files.
With ``resume=true`` (default) a run whose ``metrics.json`` exists is not redone.
"""
from __future__ import annotations

import functools
import json
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_ftb.analysis import locomotion_replays, locomotion_tracked_returns, observation_scale
from torchrl_ftb.augmentation import AUGMENTATIONS, build_supplement, merge_datasets
from torchrl_ftb.baselines import METHODS, LABEL_METHODS, run_baseline
from torchrl_ftb.data import atomic_torch_save, atomic_write_text
from torchrl_ftb.data.labels import make_scripted_labels, make_teacher, true_return
from torchrl_ftb.preference import QUERY_STRATEGIES, make_query_labels
from torchrl_ftb.datasets import dataset_kwargs, make_dataset
from torchrl_ftb.envs import check_env_matches, dynamics_oracle, env_kind, make_env, normalized_score_fn, true_reward_fn
from torchrl_ftb.policy import check_policy_sections, evaluate_policy
from torchrl_ftb.provenance import git_commit, machine_info, make_logger

PRESETS = ("cpu", "paper")
#: methods that train on the dataset's reward and so can take a generated supplement
AUGMENTABLE = ("bc", "bc10", "td3bc", "iql")


# ====================================================================
# Data
# ----


def query_strategy(cfg: DictConfig) -> str:
    """``labels.query.strategy`` (``"random"`` for configs written before the option existed)."""
    return (cfg.labels.get("query") or {}).get("strategy", "random")


def make_labels(cfg: DictConfig, trajs, *, device=None):
    """Scripted labels exactly as FTB draws them (teacher, pairs, seed, ``labels.query``).

    Methods that do not read labels get the uniform pairs whatever ``labels.query`` says (an
    active query round trains score models they would never use).
    """
    lab = cfg.labels
    horizon = lab.get("horizon")
    teacher = make_teacher(str(lab.teacher), discount=float(lab.discount),
                           horizon=None if horizon is None else int(horizon))
    if cfg.method not in LABEL_METHODS:
        return make_scripted_labels(trajs, num_pairs=int(lab.num_pairs), teacher=teacher, seed=int(lab.seed)), teacher
    sm_cfg = cfg.score_model
    labels = make_query_labels(
        trajs, num_pairs=int(lab.num_pairs), teacher=teacher, seed=int(lab.seed), **dict(lab.get("query") or {}),
        model_kwargs={k: sm_cfg.get(k) for k in ("num_cells", "num_layers", "gamma", "reward_activation",
                                                 "horizon")},
        normalize_observations=bool(sm_cfg.get("normalize_observations")), device=device,
    )
    return labels, teacher


# ====================================================================
# Bookkeeping
# -----------


def check_config(cfg: DictConfig) -> None:
    if cfg.method not in METHODS:
        raise ValueError(f"method={cfg.method!r}: unknown; choose from {sorted(METHODS)}")
    if cfg.preset not in PRESETS:
        raise ValueError(f"preset={cfg.preset!r}: unknown; choose from {list(PRESETS)}")
    kind = cfg.augmentation.kind
    if kind not in AUGMENTATIONS:
        raise ValueError(f"augmentation.kind={kind!r}: unknown; choose from {list(AUGMENTATIONS)}")
    if kind != "none" and cfg.method not in AUGMENTABLE:
        raise ValueError(f"augmentation.kind={kind!r} with method={cfg.method!r}: a supplement brings generated "
                         f"rewards, so only {list(AUGMENTABLE)} can use it")
    strategy = query_strategy(cfg)
    if strategy not in QUERY_STRATEGIES:
        raise ValueError(f"labels.query.strategy={strategy!r}: choose one of {list(QUERY_STRATEGIES)}")
    if env_kind(cfg.env.name) != "locomotion" and cfg.augmentation.get("tracked", False):  # env_kind: a known env
        raise ValueError(f"augmentation.tracked=true with env.name={cfg.env.name!r}: the tracked reading needs a "
                         "locomotion env (its simulator state is rebuilt from an observation)")
    # BC's (the BC methods') and the evaluation's numbers, before any data or training
    check_policy_sections({"bc": cfg.bc, "eval": cfg.eval} if str(cfg.method).startswith("bc") else {"eval": cfg.eval})


def supplement_readings(cfg: DictConfig, trajs) -> dict[str, Any]:
    """A locomotion supplement's simulator readings: its actions replayed open loop, and with
    ``augmentation.tracked`` its paths tracked in closed loop (the shooting tracker, on the distance scale of the
    dataset's top ``augmentation.flow.top_k`` by return: the trajectories the flow starts from)."""
    env = str(cfg.env.name)
    readings = {"replayed": lambda t: locomotion_replays(env, t)[0]}
    if cfg.augmentation.get("tracked", False):
        scale = observation_scale(trajs[true_return(trajs).argsort(descending=True)[: int(cfg.augmentation.flow.top_k)]])
        readings["tracked"] = lambda t: locomotion_tracked_returns(env, t, scale=scale)[0]
    return readings


def make_supplement(cfg: DictConfig, trajs, *, device, logger) -> tuple[Any, dict | None]:
    """The dataset merged with the augmentation's generated trajectories (``kind=none``: as is)."""
    aug = cfg.augmentation
    if aug.kind == "none":
        return trajs, None
    locomotion = env_kind(cfg.env.name) == "locomotion"  # its simulator state is rebuilt from an observation
    supplement, info = build_supplement(
        str(aug.kind), trajs, cache_dir=Path(str(aug.cache_dir)).expanduser().resolve(),
        diffuser=OmegaConf.to_container(aug.diffuser, resolve=True),
        flow=OmegaConf.to_container(aug.flow, resolve=True),
        synthetic={} if aug.synthetic.num_samples is None else {"num_samples": int(aug.synthetic.num_samples)},
        num_blocks=int(aug.num_blocks), seed=int(cfg.seed),
        true_reward_fn=true_reward_fn(cfg.env.name) if aug.true_reward else None,
        oracle_step=dynamics_oracle(cfg.env.name) if locomotion else None,
        readings=supplement_readings(cfg, trajs) if locomotion else None,
        device=device, logger=logger, progress=bool(cfg.progress),
    )
    merged = merge_datasets(trajs, supplement) if supplement.batch_size[0] else trajs
    print(f"[baselines] augmentation {aug.kind}: +{info['num_trajectories']} trajectories "
          f"(+{info['num_transitions']} transitions to {info['dataset_transitions']}) from {info['path']}")
    return merged, info


def _report(metrics: dict[str, Any]) -> str:
    ev = metrics["eval"]
    lines = [
        f"# Baseline `{metrics['method']}` on `{metrics['env']}` (seed {metrics['seed']})",
        "",
        f"{METHODS[metrics['method']]}; labels: {metrics['labels']['num_pairs']} pairs, "
        f"teacher `{metrics['labels']['teacher']}`" + ("" if metrics["uses_labels"] else " (not used by this method)"),
        "",
        "| metric | value |", "|---|---|",
        f"| score ({metrics['score_name']}) | {metrics['score']:.4f} |",
        f"| return (mean ± std) | {ev['return_mean']:.2f} ± {ev['return_std']:.2f} |",
        f"| episode length | {ev['length_mean']:.1f} |",
        f"| evaluation episodes | {ev['num_episodes']} |",
        f"| wall time | {metrics['wall_time_s']:.0f} s |",
    ]
    aug = metrics.get("augmentation") or {}
    if aug.get("kind", "none") != "none":
        lines += ["", f"Data augmented with `{aug['kind']}` ({AUGMENTATIONS[aug['kind']]}): "
                  f"+{aug['num_trajectories']} trajectories, +{aug['num_transitions']} transitions "
                  f"to the dataset's {aug['dataset_transitions']}.", "",
                  "| return | mean | max |", "|---|---|---|",
                  f"| dataset | {aug['dataset_return_mean']:.2f} | {aug['dataset_return_max']:.2f} |"]
        for name, key in (("supplement, generated reward", "generated_return"), ("supplement, true reward", "true_return"),
                          ("supplement, actions replayed open loop", "replayed_return"),
                          ("supplement, paths tracked in closed loop", "tracked_return")):
            if aug.get(f"{key}_mean") is not None:
                lines.append(f"| {name} | {aug[f'{key}_mean']:.2f} | {aug[f'{key}_max']:.2f} |")
        if aug.get("dynamics_error_mean") is not None:
            lines += ["", f"Supplement dynamics error (mean |s' - oracle(s, a)| per dimension): "
                      f"{aug['dynamics_error_mean']:.4f}."]
    return "\n".join(lines) + "\n"


# ====================================================================
# Main
# ----


def run(cfg: DictConfig) -> dict[str, Any]:
    """Run one baseline cell in ``cfg.run_dir``; returns (and writes) the metrics dict."""
    check_config(cfg)
    run_dir = Path(cfg.run_dir).expanduser().resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    metrics_file = run_dir / "metrics.json"
    if cfg.resume and metrics_file.exists():
        done = json.loads(metrics_file.read_text())
        done_kind = (done.get("augmentation") or {}).get("kind", "none")
        if (done.get("method"), done_kind) != (cfg.method, cfg.augmentation.kind):
            raise ValueError(f"{metrics_file}: this run directory holds a finished run of method={done.get('method')!r}"
                             f" augmentation.kind={done_kind!r}, not method={cfg.method!r} augmentation.kind="
                             f"{cfg.augmentation.kind!r}; pass another run_dir")
        print(f"[baselines] {metrics_file} exists (resume=true): nothing to do")
        return done
    start = time.perf_counter()
    if int(cfg.num_threads) > 0:
        torch.set_num_threads(int(cfg.num_threads))
    torch.manual_seed(int(cfg.seed))
    atomic_write_text(run_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    device = torch.device(cfg.device)
    logger = make_logger(cfg.logger.backend, log_dir=run_dir / "logs",
                         experiment_name=f"{cfg.method}_{cfg.env.name}_seed{cfg.seed}",
                         project=cfg.logger.project_name, mode=cfg.logger.mode,
                         config=OmegaConf.to_container(cfg, resolve=True))

    # FTB's data and evaluation env (torchrl_ftb.datasets.make_dataset / torchrl_ftb.envs.make_env)
    name, kind, limit = cfg.env.name, env_kind(cfg.env.name), int(cfg.env.max_episode_steps)
    trajs, meta = make_dataset(name, **dataset_kwargs(name, cfg.dataset, max_episode_steps=limit,
                                                      progress=bool(cfg.progress)))
    eval_env = functools.partial(make_env, name, seed=int(cfg.eval.seed), toy_horizon=int(cfg.dataset.horizon),
                                 max_episode_steps=None if kind == "locomotion" else limit)  # locomotion: 1000
    check_env_matches(eval_env, trajs, name=name)
    labels, teacher = make_labels(cfg, trajs, device=device)
    data, augmentation = make_supplement(cfg, trajs, device=device, logger=logger)
    result = run_baseline(
        cfg.method, data, labels=labels, seed=int(cfg.seed),
        network=OmegaConf.to_container(cfg.network, resolve=True),
        bc=OmegaConf.to_container(cfg.bc, resolve=True),
        iql=OmegaConf.to_container(cfg.iql, resolve=True),
        td3bc=OmegaConf.to_container(cfg.td3bc, resolve=True),
        top_fraction=float(cfg.bc10.top_fraction), teacher=teacher,
        reward_normalization=str(cfg.reward_normalization),
        reward_model={k: cfg.score_model.get(k) for k in ("num_cells", "num_layers", "gamma", "reward_activation",
                                                           "horizon", "normalize_observations")},
        reward_training={k: cfg.score_model[k] for k in ("steps", "batch_size", "lr", "eval_fraction")},
        oprl_members=int(cfg.oprl.members), logger=logger, progress=bool(cfg.progress), device=device,
    )
    atomic_torch_save({"method": cfg.method, "actor": result.actor.state_dict()}, run_dir / "actor.pt")

    ev = evaluate_policy(  # exactly FTB's evaluation: same env seed, episodes, stop rule
        eval_env, result.actor,
        num_episodes=cfg.eval.num_episodes, seed=int(cfg.eval.seed),
        max_steps=cfg.eval.max_steps,
        num_envs=cfg.eval.num_envs,
        stop_on_success=bool(cfg.eval.stop_on_success) and kind == "metaworld",
        normalized_score_fn=normalized_score_fn(cfg.env.name), progress=bool(cfg.progress),
    )
    if kind == "metaworld":
        score_name, score = "success_rate", ev["success_rate"]
    elif kind == "locomotion":
        score_name, score = "d4rl_normalized_score", ev["normalized_score"]
    else:
        score_name, score = "return_mean", ev["return_mean"]
    metrics = {
        "method": cfg.method, "description": METHODS[cfg.method], "env": cfg.env.name, "seed": int(cfg.seed),
        "preset": cfg.preset, "score_name": score_name, "score": float(score), "eval": ev,
        "uses_labels": cfg.method in LABEL_METHODS,
        "labels": {"num_pairs": int(labels.batch_size[0]), "teacher": teacher.name, "seed": int(cfg.labels.seed),
                   "query": query_strategy(cfg) if cfg.method in LABEL_METHODS else "random"},
        "dataset": {k: v for k, v in (meta or {}).items() if isinstance(v, (int, float, str, bool))},
        "augmentation": {"kind": "none"} if augmentation is None else _jsonable(augmentation),
        "train": _jsonable(result.info),
        "wall_time_s": time.perf_counter() - start,
        "command": " ".join(sys.argv), "git_commit": git_commit(), "machine": machine_info(),
    }
    if logger is not None:
        for k in ("score", "wall_time_s"):
            logger.log_scalar(f"final/{k}", float(metrics[k]), step=0)
    atomic_write_text(run_dir / "report.md", _report(metrics))
    atomic_write_text(metrics_file, json.dumps(metrics, indent=2))  # last: marks the run finished
    print(f"[baselines] {cfg.method} on {cfg.env.name} seed {cfg.seed}: {score_name} = {score:.4f} "
          f"({metrics['wall_time_s']:.0f} s) -> {run_dir}")
    return metrics


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return obj.tolist()
    if isinstance(obj, (int, float, str, bool)) or obj is None:
        return obj
    return str(obj)


@hydra.main(config_path="config", config_name="baselines", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
