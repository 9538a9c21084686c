"""Does the FTB policy's success follow the successes in the top-k s_psi picks? (issue #5, analysis)

FTB's BC policy learns from the final set: the s_psi top-k of the dataset plus the samples the
flow accepted. Wherever the flow accepts few samples (every Meta-World ``cpu`` cell: 0-39 of
100) that set is nearly the top-k itself, so the share of *successful* trajectories in it should
bound what BC can copy. For each Table-1 cell given (``bench/table1.py`` JSONs) whose run
directory still exists, this reads the run's own scores (``checkpoints/blocks.pt``, no
training), the dataset's per-trajectory success, and reports the top-k success share
(:func:`torchrl_ftb.preference.top_k_mean`, what the recipe records as
``score_quality.top_k_success`` since session 14) next to the cell's policy success, and which of the
generator's behaviour groups the top-k comes from (Meta-World: ``expert`` = the task's policy on one
goal, ``within`` = the same on a new goal every episode, ``random``, ``cross`` = other tasks'
policies) with the successes of each. Cells whose
run directory is gone are listed as skipped. JSON (command, config, commit, machine) and a
scatter plot of policy success against the top-k success share. Not a test.

    python bench/topk_success.py --cells bench/results/table1_v2/ftb__*.json bench/results/table1_v2_active/ftb__*.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.analysis.plots import save_figure  # noqa: E402
from torchrl_ftb.data import trajectory_lengths  # noqa: E402
from torchrl_ftb.data.labels import SuccessTeacher  # noqa: E402
from torchrl_ftb.datasets import dataset_kwargs, make_dataset  # noqa: E402
from torchrl_ftb.preference import correlations, top_k_mean  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

KS = (25, 50, 100, 150)


def cell_report(cell: dict, run_dir: Path, cache: dict) -> dict:
    """Top-k success share of one cell's run, from its saved block scores."""
    cfg = OmegaConf.load(run_dir / "config.yaml")
    name = str(cfg.env.name)
    key = (name, json.dumps(OmegaConf.to_container(cfg.dataset, resolve=True), sort_keys=True))
    if key not in cache:
        trajs, meta = make_dataset(name, **dataset_kwargs(name, cfg.dataset, progress=False,
                                                          max_episode_steps=int(cfg.env.max_episode_steps)))
        if ("next", "success") not in trajs.keys(True):
            raise ValueError(f"{run_dir}: the dataset of {name!r} has no ('next', 'success') flag (Meta-World only)")
        groups = (meta["per_trajectory"]["group"], list(meta["groups"])) if "per_trajectory" in meta else None
        cache[key] = SuccessTeacher().succeeded(trajs).float(), trajectory_lengths(trajs).float(), groups
    success, lengths, groups = cache[key]
    blocks = torch.load(run_dir / "checkpoints" / "blocks.pt", weights_only=True)
    scores = blocks["scores"]
    if scores.shape != success.shape:
        raise ValueError(f"{run_dir}/checkpoints/blocks.pt: {scores.numel()} scores for a dataset of "
                         f"{success.numel()} trajectories")
    k = int(cfg.flow.top_k)
    flow = cell["metrics"]["flow"]
    composition = {}
    if groups is not None:  # which behaviour the top-k comes from (the generator's groups), and its successes
        top = scores.topk(min(k, scores.numel())).indices
        group, names = groups
        composition = {
            "top_k_groups": {n: int((group[top] == i).sum()) for i, n in enumerate(names)},
            "top_k_group_successes": {n: int(success[top][group[top] == i].sum()) for i, n in enumerate(names)},
        }
    return {
        "env": name, "teacher": str(cfg.labels.teacher), "seed": int(cfg.seed),
        "labels": str(OmegaConf.select(cfg, "labels.query.strategy", default="random")),
        "score_horizon": OmegaConf.select(cfg, "score_model.horizon", default=None),
        "top_k": k, "top_k_success": top_k_mean(scores, success, k), "dataset_success": float(success.mean()),
        "spearman_success": correlations(scores, success)["spearman"],
        # the same share for other k, and how long the top-scored and the (un)successful trajectories are
        "top_k_success_by_k": {str(j): top_k_mean(scores, success, j) for j in KS if j <= scores.numel()},
        "top25_length_mean": top_k_mean(scores, lengths, min(25, scores.numel())),
        "length_mean_success": float(lengths[success > 0].mean()) if bool((success > 0).any()) else None,
        "length_mean_failure": float(lengths[success == 0].mean()) if bool((success == 0).any()) else None,
        "fraction_generated_in_final": float(flow["fraction_generated_in_final"]),
        **composition,
        "policy_success": float(cell["metrics"]["eval"]["success_rate"]),
        "run_dir": str(run_dir),
    }


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    markers = {"return": "o", "success": "^"}
    envs = sorted({r["env"] for r in rows})
    colors = {e: f"C{i}" for i, e in enumerate(envs)}
    for r in rows:
        color = colors[r["env"]]
        ax.scatter(r["top_k_success"], r["policy_success"], marker=markers.get(r["teacher"], "s"), s=40,
                   edgecolors=color, facecolors="none" if r["labels"] == "random" else color)
    for e in envs:
        ax.scatter([], [], color=colors[e], label=e)
    ax.scatter([], [], marker="o", color="grey", label="return teacher")
    ax.scatter([], [], marker="^", color="grey", label="success teacher")
    ax.scatter([], [], marker="o", facecolors="none", edgecolors="grey", label="uniform labels (hollow)")
    ax.plot([0, 1], [0, 1], "k:", lw=0.8)
    ax.set_xlabel("successes in the s_psi top-k (share)")
    ax.set_ylabel("FTB policy success rate")
    c = correlations(torch.tensor([r["top_k_success"] for r in rows]), torch.tensor([r["policy_success"] for r in rows]))
    ax.set_title(f"{len(rows)} FTB cells: pearson {c['pearson']:.2f}, spearman {c['spearman']:.2f}", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    return save_figure(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", nargs="+", type=Path, required=True, help="bench/table1.py FTB cell JSONs")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "topk_success.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    record = {**run_record(config={"cells": [str(c) for c in args.cells]}), "cells": {}, "skipped": {}}
    cache: dict = {}
    for path in args.cells:
        cell = json.loads(path.read_text())
        run_dir = ROOT / cell["run_dir"]  # an absolute run_dir stays as it is
        if not (run_dir / "checkpoints" / "blocks.pt").is_file():
            record["skipped"][str(path)] = f"run directory {cell['run_dir']} (or its blocks checkpoint) is gone"
            continue
        rep = cell_report(cell, run_dir, cache)
        record["cells"][str(path)] = rep
        groups = " ".join(f"{g} {n}/{rep['top_k_group_successes'][g]}" for g, n in rep.get("top_k_groups", {}).items())
        print(f"{rep['env']} {rep['teacher']} {rep['labels']} seed {rep['seed']}: top-k success {rep['top_k_success']:.2f} "
              f"(dataset {rep['dataset_success']:.2f}; groups, count/successes: {groups}) -> policy "
              f"{rep['policy_success']:.2f}", flush=True)
    rows = list(record["cells"].values())
    if len(rows) >= 2:
        c = correlations(torch.tensor([r["top_k_success"] for r in rows]),
                         torch.tensor([r["policy_success"] for r in rows]))
        record["correlation_top_k_success_vs_policy"] = c
        grouped = [r for r in rows if "top_k_group_successes" in r]
        if len(grouped) >= 2:  # which successes the policy follows: per behaviour group, Spearman over cells
            policy = torch.tensor([r["policy_success"] for r in grouped])
            record["spearman_policy_vs_group_successes"] = {
                g: correlations(torch.tensor([float(r["top_k_group_successes"][g]) for r in grouped]), policy)["spearman"]
                for g in grouped[0]["top_k_group_successes"]
                if len({r["top_k_group_successes"][g] for r in grouped}) > 1}  # a constant group has none
            print("spearman(policy, successes of each group in the top-k):",
                  {g: round(v, 3) for g, v in record["spearman_policy_vs_group_successes"].items()})
        png = plot(rows, args.out.with_suffix(".png"))
        record["plot"] = str(png.relative_to(ROOT) if png.is_relative_to(ROOT) else png)
        print(f"across {len(rows)} cells: pearson {c['pearson']:.3f}, spearman {c['spearman']:.3f}")
    write_json(args.out, record)
    print(f"-> {args.out} ({len(rows)} cells, {len(record['skipped'])} skipped)")


if __name__ == "__main__":
    main()
