"""Where does s_psi's ranking go wrong? Spearman with the true return, split by behaviour group.

Our Meta-World datasets hold four behaviour groups (IPL recipe: expert, within-env, random,
cross-env; ``meta["per_trajectory"]["group"]``). For the score model of each given FTB run
(``recipes/ftb_offline.py``: its ``checkpoints/score_model.pt`` and dataset) this reports the
overall Spearman(s_psi, true return), per group the mean return / length / score and the
within-group Spearman, how many of the run's labels compare two trajectories of each pair of
groups, and two reference points: the Spearman of a score that knew only each
trajectory's group (the group's mean true return: how far ranking the groups alone goes) and
that of the trajectory length. No training: it reads the runs' checkpoints. JSON to
``bench/results/score_groups.json`` (command, config, commit, machine).

Usage::

    python bench/score_groups.py --run-dirs outputs/exp/bp-identity-v2 outputs/exp/drawer-v2 ...
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_diagnostics import spearman  # noqa: E402

from torchrl_ftb.data import load_labels  # noqa: E402
from torchrl_ftb.data.labels import true_return  # noqa: E402
from torchrl_ftb.datasets import dataset_kwargs, make_dataset  # noqa: E402
from torchrl_ftb.preference import load_score_model, score_trajectories  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def group_report(scores: torch.Tensor, returns: torch.Tensor, lengths: torch.Tensor, groups: torch.Tensor,
                 names: list[str]) -> dict:
    """Overall / per-group Spearman and the group-only and length-only reference points."""
    group_mean = torch.zeros_like(returns)
    per_group = {}
    for g, name in enumerate(names):
        idx = groups == g
        if not bool(idx.any()):
            continue
        group_mean[idx] = returns[idx].mean()
        per_group[name] = {
            "n": int(idx.sum()), "return_mean": float(returns[idx].mean()), "return_std": float(returns[idx].std()),
            "length_mean": float(lengths[idx].mean()), "score_mean": float(scores[idx].mean()),
            "spearman_within": spearman(scores[idx], returns[idx]),
        }
    means = torch.tensor([v["score_mean"] for v in per_group.values()])
    ret_means = torch.tensor([v["return_mean"] for v in per_group.values()])
    return {
        "spearman": spearman(scores, returns),
        "spearman_group_mean_return": spearman(group_mean, returns),
        "spearman_length": spearman(lengths, returns),
        "spearman_group_means": spearman(means, ret_means),  # do the groups' mean scores order them right?
        "per_group": per_group,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "score_groups.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    record = {**run_record(config={"run_dirs": [str(r) for r in args.run_dirs]}), "runs": {}}
    for run in args.run_dirs:
        cfg = OmegaConf.load(run / "config.yaml")
        name = str(cfg.env.name)
        trajs, meta = make_dataset(name, **dataset_kwargs(name, cfg.dataset, progress=False,
                                                          max_episode_steps=int(cfg.env.max_episode_steps)))
        if "per_trajectory" not in meta or "group" not in meta["per_trajectory"].keys():
            raise ValueError(f"{run}: the dataset of {name!r} has no behaviour groups (Meta-World only)")
        model = load_score_model(run / "checkpoints" / "score_model.pt")
        scores = score_trajectories(model, trajs.select("observation", "action", "mask")).double()
        returns = true_return(trajs, discount=float(cfg.labels.discount))
        lengths = trajs.get("mask").sum(-1).double()
        rep = group_report(scores, returns, lengths, meta["per_trajectory"]["group"], list(meta["groups"]))
        labels, _ = load_labels(run / "checkpoints" / "labels")
        g = meta["per_trajectory"]["group"]
        g0, g1 = g[labels.get("index0")], g[labels.get("index1")]
        names = list(meta["groups"])
        rep["labels_per_group_pair"] = {
            f"{names[a]}-{names[b]}": int((((g0 == a) & (g1 == b)) | ((g0 == b) & (g1 == a))).sum())
            for a in range(len(names)) for b in range(a, len(names))}
        rep.update(env=name, seed=int(cfg.seed), teacher=str(cfg.labels.teacher))
        record["runs"][str(run)] = rep
        within = " ".join(f"{k} {v['spearman_within']:+.2f}" for k, v in rep["per_group"].items())
        print(f"{name} seed {cfg.seed}: spearman {rep['spearman']:.3f} | group-only {rep['spearman_group_mean_return']:.3f}"
              f" length-only {rep['spearman_length']:.3f} | within: {within}", flush=True)
        write_json(args.out, record)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
