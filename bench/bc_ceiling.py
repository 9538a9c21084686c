"""What can FTB's BC policy do with a hand-picked set? The ceiling of any ranking (issue #5, analysis).

FTB's Meta-World policy is BC on (nearly) the s_psi top-100. Across the Table-1 cells its success
follows which trajectories that top-100 holds (``bench/topk_success.py``), and even a top-100 of
90-97 % successes leaves plate-slide at 0.55-0.75. This bench asks what the same BC (the recipe's
``bc`` settings and actor, the same evaluation) does when the set is chosen with the dataset's own
labels instead of s_psi, i.e. what a perfect score model could hand it:

* ``on_task``: successful episodes of the task's own scripted policy (groups ``expert`` and
  ``within``), up to ``--k`` of them drawn at random;
* ``within``: successful ``within`` episodes only (the task's policy, a new goal every episode);
* ``expert``: successful ``expert`` episodes only (the task's policy, *one* fixed goal, the
  dataset seed's);
* ``any``: up to ``--k`` successful episodes of any group (cross-env successes included, which come
  from *other* tasks' scripted policies).

``--with-failures`` drops the success condition: every episode of the subset's groups is a candidate
(up to ``--k`` drawn at random), i.e. BC asked to average the noisy scripted policy itself, which is
what a task with almost no successes (assembly: 4 in 400, all ``expert``) leaves a ranking to pick.

Evaluation draws a new goal every episode (the recipe's ``eval`` settings), so ``expert`` vs
``within`` measures how much goal diversity BC needs, and ``on_task`` vs ``any`` what cross-env
successes in the set cost. ``--obs-stats dataset`` z-scores the actor's observations with the whole
dataset's mean/std instead of the chosen set's (a one-goal set has near-constant goal dims, whose
floored std turns a new goal into inputs of hundreds of standard deviations). Not a test; JSON with command, config, commit and machine:

    python bench/bc_ceiling.py --tasks button-press-v3,plate-slide-v3 --subsets on_task,within,expert,any
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.data import trajectories_to_flat  # noqa: E402
from torchrl_ftb.data.labels import SuccessTeacher  # noqa: E402
from torchrl_ftb.datasets import dataset_kwargs, make_dataset  # noqa: E402
from torchrl_ftb.envs import make_env  # noqa: E402
from torchrl_ftb.policy import evaluate_policy, make_bc_actor_for, make_transition_buffer, train_bc  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

SUBSETS = {
    "on_task": ("expert", "within"),
    "within": ("within",),
    "expert": ("expert",),
    "any": ("expert", "within", "random", "cross"),
}


def select(group: torch.Tensor, success: torch.Tensor, groups: list[str], subset: str, *, k: int,
           generator: torch.Generator, with_failures: bool = False) -> torch.Tensor:
    """Indices of up to ``k`` trajectories whose group is in ``SUBSETS[subset]``: successful ones only,
    or any of them with ``with_failures``."""
    wanted = torch.tensor([groups.index(g) for g in SUBSETS[subset]])
    keep = torch.isin(group, wanted) if with_failures else success & torch.isin(group, wanted)
    pool = torch.nonzero(keep).squeeze(-1)
    if pool.numel() > k:
        pool = pool[torch.randperm(pool.numel(), generator=generator)[:k]]
    return pool


def load_task(task: str, cfg) -> tuple:
    """The task's cached dataset, its per-trajectory group and success."""
    trajs, meta = make_dataset(task, **dataset_kwargs(task, cfg.dataset, progress=False,
                                                      max_episode_steps=int(cfg.env.max_episode_steps)))
    return trajs, meta, meta["per_trajectory"]["group"], SuccessTeacher().succeeded(trajs)


def run_cell(task: str, idx: torch.Tensor, seed: int, cfg, data: tuple, *, episodes: int, steps: int,
             obs_stats: str = "subset") -> dict:
    """BC (the recipe's settings) on trajectories ``idx`` of the task's dataset, then evaluation."""
    trajs, meta, group, success = data
    if idx.numel() == 0:
        return {"num_trajectories": 0, "success_rate": None, "note": "no trajectory in this subset"}
    chosen = trajs[idx]
    flat = trajectories_to_flat(chosen.select("observation", "action", "mask"))
    # the actor's observation z-score: from the BC set itself (the recipe's) or from the whole dataset
    source = None if obs_stats == "subset" else trajectories_to_flat(trajs.select("observation", "action", "mask"))
    torch.manual_seed(seed)
    actor = make_bc_actor_for(flat, hidden=tuple(cfg.bc.hidden), statistics_from=source)
    b = cfg.bc
    t0 = time.perf_counter()
    out = train_bc(actor, make_transition_buffer(flat, batch_size=int(b.batch_size), seed=seed), steps=steps,
                   batch_size=int(b.batch_size), lr=float(b.lr), weight_decay=float(b.weight_decay), seed=seed,
                   progress=False)
    bc_s = time.perf_counter() - t0
    eval_env = functools.partial(make_env, task, seed=int(cfg.eval.seed), max_episode_steps=int(cfg.env.max_episode_steps))
    t0 = time.perf_counter()
    ev = evaluate_policy(eval_env, actor, num_episodes=episodes, seed=int(cfg.eval.seed),
                         max_steps=cfg.eval.max_steps,
                         stop_on_success=True)
    counts = torch.bincount(group[idx], minlength=len(meta["groups"])).tolist()
    succ = [int(success[idx][group[idx] == i].sum()) for i in range(len(meta["groups"]))]
    return {
        "num_trajectories": int(idx.numel()), "num_transitions": int(flat.numel()),
        "groups": dict(zip(meta["groups"], counts)), "group_successes": dict(zip(meta["groups"], succ)),
        "final_loss": out["loss"],
        "success_rate": float(ev["success_rate"]), "length_mean": float(ev["length_mean"]),
        "num_episodes": int(ev["num_episodes"]), "bc_seconds": bc_s, "eval_seconds": time.perf_counter() - t0,
        "dataset_path": meta.get("path"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", default="button-press-v3,drawer-open-v3,plate-slide-v3,sweep-into-v3")
    parser.add_argument("--subsets", default="on_task,within,expert,any")
    parser.add_argument("--seeds", default="0", help="BC / subset-draw seeds")
    parser.add_argument("--run-dirs", nargs="+", type=Path, default=None,
                        help="instead of the subsets: BC on the top --k of each FTB run's own s_psi scores "
                             "(checkpoints/blocks.pt; the run's task and seed), i.e. its final set without the flow")
    parser.add_argument("--k", type=int, default=100, help="at most this many trajectories (FTB's top_k)")
    parser.add_argument("--episodes", type=int, default=50, help="evaluation episodes per cell")
    parser.add_argument("--steps", type=int, default=None, help="BC steps (default: the cpu preset's)")
    parser.add_argument("--obs-stats", choices=("subset", "dataset"), default="subset",
                        help="the BC actor's observation mean/std: of the chosen set (the recipe's) or of the dataset")
    parser.add_argument("--with-failures", action="store_true",
                        help="candidates: every episode of the subset's groups, not only the successful ones")
    parser.add_argument("--dataset-overrides", nargs="+", default=[], metavar="KEY=VALUE",
                        help="with the subsets: the recipe's dataset.* settings to change, e.g. noise=0.3 (the "
                             "--run-dirs cells use each run's own dataset settings)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "bc_ceiling.json")
    args = parser.parse_args()
    unknown = set(args.subsets.split(",")) - set(SUBSETS)
    if unknown:
        parser.error(f"--subsets: unknown {sorted(unknown)}; choose from {list(SUBSETS)}")
    torch.set_num_threads(1)
    cfg = OmegaConf.load(ROOT / "recipes" / "config" / "ftb_offline.yaml")
    if args.dataset_overrides:
        if args.run_dirs:
            parser.error("--dataset-overrides: the --run-dirs cells use each run's own dataset settings")
        try:
            cfg.dataset = OmegaConf.merge(cfg.dataset, OmegaConf.from_dotlist(args.dataset_overrides))
        except Exception as err:  # omegaconf's parse errors: name the option
            parser.error(f"--dataset-overrides {args.dataset_overrides}: {err}")
    steps = args.steps if args.steps is not None else int(cfg.presets.cpu.bc_steps)
    config = {**vars(args), "out": str(args.out), "steps": steps,
              "bc": OmegaConf.to_container(cfg.bc), "eval": {"seed": int(cfg.eval.seed), "max_steps": cfg.eval.max_steps}}
    del config["bc"]["steps"], config["bc"]["checkpoint_every"]  # preset interpolations; steps above
    record = {**run_record(config=config), "cells": {}}
    if args.out.is_file():  # resume: keep finished cells of the same command
        old = json.loads(args.out.read_text())
        same = {"k", "episodes", "steps", "obs_stats", "with_failures", "dataset_overrides"}
        if any(old.get("config", {}).get(key, parser.get_default(key)) != config[key] for key in same):
            parser.error(f"{args.out} holds cells of other options ({sorted(same)}): pass another --out")
        record["cells"] = old.get("cells", {})
    jobs = []  # (key, task, seed, config of the dataset, its size or None, selection)
    if args.run_dirs:
        for run_dir in args.run_dirs:
            run_cfg = OmegaConf.load(run_dir / "config.yaml")
            scores = torch.load(run_dir / "checkpoints" / "blocks.pt", weights_only=True)["scores"]
            # the run's own dataset (its noise, groups, ...): its scores index that one
            jobs.append((f"{run_cfg.env.name}/s_psi_top{args.k}/{run_dir}", str(run_cfg.env.name), int(run_cfg.seed),
                         run_cfg, scores.numel(), lambda data, scores=scores: scores.topk(min(args.k, scores.numel())).indices))
    else:
        for task in args.tasks.split(","):
            for subset in args.subsets.split(","):
                for seed in (int(s) for s in args.seeds.split(",")):
                    name = subset + ("+failures" if args.with_failures else "")
                    jobs.append((f"{task}/{name}/seed{seed}", task, seed, cfg, None,
                                 lambda data, subset=subset, seed=seed: select(
                                     data[2], data[3], list(data[1]["groups"]), subset, k=args.k,
                                     generator=torch.Generator().manual_seed(seed),
                                     with_failures=args.with_failures)))
    datasets: dict = {}
    for key, task, seed, data_cfg, size, selection in jobs:
        if key in record["cells"]:
            continue
        data_key = (task, json.dumps(OmegaConf.to_container(data_cfg.dataset, resolve=True), sort_keys=True))
        if data_key not in datasets:
            datasets[data_key] = load_task(task, data_cfg)
        data = datasets[data_key]
        if size is not None and data[0].batch_size[0] != size:
            raise ValueError(f"{key}: the run's scores cover {size} trajectories, its dataset "
                             f"{data[1].get('path')} has {data[0].batch_size[0]}")
        cell = run_cell(task, selection(data), seed, cfg, data, episodes=args.episodes,
                        steps=steps, obs_stats=args.obs_stats)
        record["cells"][key] = cell
        write_json(args.out, record)
        print(f"{key}: {cell['num_trajectories']} trajectories {cell.get('groups')} -> success "
              f"{cell['success_rate']}", flush=True)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
