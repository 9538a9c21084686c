"""Benchmark: IPL-style Meta-World dataset generation speed and true-reward oracle error.

Usage: python bench/metaworld_dataset.py --task button-press-v3 --workers 2
Writes bench/results/metaworld_dataset-<task>.json (command, config, git commit, machine, results).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from torchrl_ftb.provenance import run_record, write_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="button-press-v3")
    parser.add_argument("--episodes-per-group", type=int, default=100)
    parser.add_argument("--noise", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--error-episodes-per-group", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    from torchrl_ftb.datasets import dataset_stats, make_metaworld_dataset
    from torchrl_ftb.envs import metaworld_reward_error

    with tempfile.TemporaryDirectory() as cache:  # fresh cache: measure generation, then loading
        start = time.perf_counter()
        td, meta = make_metaworld_dataset(args.task, episodes_per_group=args.episodes_per_group, noise=args.noise,
                                          seed=args.seed, cache_dir=cache, num_workers=args.workers, progress=False)
        gen_s = time.perf_counter() - start
        start = time.perf_counter()
        make_metaworld_dataset(args.task, episodes_per_group=args.episodes_per_group, noise=args.noise,
                               seed=args.seed, cache_dir=cache, progress=False)
        load_s = time.perf_counter() - start
    per = meta["per_trajectory"]
    steps = int(td["mask"].sum())
    errors = {}
    for g, name in enumerate(meta["groups"]):
        idx = (per["group"] == g).nonzero().squeeze(-1)[: args.error_episodes_per_group]
        errors[name] = {
            "next_observation": metaworld_reward_error(args.task, td[idx]),
            "shifted_observation": metaworld_reward_error(args.task, td[idx], use_next_observation=False),
        }
    out = {
        **run_record(config=vars(args)),
        "results": {
            "generation_seconds": round(gen_s, 2),
            "load_seconds": round(load_s, 3),
            "transitions": steps,
            "steps_per_second": round(steps / gen_s, 1),
            "stats": dataset_stats(td, per, groups=meta["groups"]),
            "reward_error": errors,
        },
    }
    write_json(Path(__file__).parent / "results" / f"metaworld_dataset-{args.task}.json", out)
    print(json.dumps(out["results"], indent=2))


if __name__ == "__main__":
    main()
