"""Generate (or load from the cache) an offline dataset and print per-group statistics.

Usage:
    python recipes/make_dataset.py --env button-press-v3 \
        [--episodes-per-group 100 --noise 1.0 --seed 0 --max-steps 500 --out DIR --workers 2]
        [--groups expert within random]   # Meta-World: a subset of expert/within/random/cross

The generator is looked up by env name in ``torchrl_ftb.datasets.registry`` (Meta-World v3
tasks today; any module that registers itself is picked up without changing this script).
"""
from __future__ import annotations

import argparse
import json

from torchrl_ftb.datasets import dataset_stats, format_stats, get_dataset_generator


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description="Generate/load an offline dataset and print its statistics.")
    parser.add_argument("--env", required=True, help="env/task name, e.g. button-press-v3")
    parser.add_argument("--episodes-per-group", type=int, default=None)
    parser.add_argument("--noise", type=float, default=None, help="Gaussian action-noise std (epsilon)")
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--max-steps", type=int, default=None, help="time limit / padded horizon")
    parser.add_argument("--out", default=None, help="cache dir (default $TORCHRL_FTB_DATA or ~/.cache/torchrl_ftb/datasets)")
    parser.add_argument("--workers", type=int, default=None, help="worker processes")
    parser.add_argument("--groups", nargs="+", default=None,
                        help="Meta-World: which groups to generate (default all: expert within random cross)")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the statistics as JSON")
    return parser.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    generator = get_dataset_generator(args.env)
    options = {
        "episodes_per_group": args.episodes_per_group,
        "noise": args.noise,
        "seed": args.seed,
        "max_steps": args.max_steps,
        "out": args.out,
        "num_workers": args.workers,
        "groups": args.groups,
    }
    options = {k: v for k, v in options.items() if v is not None}  # generator defaults otherwise
    td, meta = generator.fn(args.env, progress=not args.no_progress, **options)
    stats = dataset_stats(td, meta["per_trajectory"], groups=meta["groups"])
    print(f"dataset: {meta.get('path')}  [{td.batch_size[0]} trajectories x horizon {td.batch_size[1]}]")
    print(json.dumps(stats, indent=2) if args.json else format_stats(stats))
    return stats


if __name__ == "__main__":
    main()
