"""How much of a trajectory's true return survives temporal coarsening and refinement?

A diffuser trained on coarsened trajectories (``bench/diffuser_conditioning.py --stride``) can at best reproduce
its data's round trip: :func:`~torchrl_ftb.data.coarsen_trajectories` then
:func:`~torchrl_ftb.data.refine_trajectories`. This bench reads an FTB run's dataset and blocks, and for each
stride gives the true-reward oracle's return of every trajectory before and after the round trip, per block
(the stop-rule fill after the stop-rule cut with ``--horizon 500 --streak 25``, as the flow reports it).
``--hold`` starts each round trip from the trajectories held at their last step to the full horizon
(:func:`~torchrl_ftb.data.hold_last_step`, what ``bench/diffuser_conditioning.py --hold`` trains on; the stop rule
cuts them again), and accepts stride 1: the hold alone.

Usage::

    python bench/coarsen_round_trip.py --run-dir outputs/exp/bp --strides 2 5 10 --horizon 500 --streak 25
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_diagnostics import load_run, sample_true_return  # noqa: E402

from torchrl_ftb.data import coarsen_trajectories, hold_last_step, refine_trajectories  # noqa: E402
from torchrl_ftb.envs import true_reward_fn  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def per_block(before: torch.Tensor, after: torch.Tensor, ids: torch.Tensor) -> dict[str, dict[str, float]]:
    """Mean true return before / after the round trip and its ratio, per block (1-based) and over all."""
    out = {}
    for name, sel in [(str(k + 1), ids == k) for k in range(int(ids.max()) + 1)] + [("all", ids >= 0)]:
        b, a = before[sel].mean().item(), after[sel].mean().item()
        out[name] = {"n": int(sel.sum()), "before": b, "after": a, "kept": a / b if b else float("nan"),
                     "max_before": before[sel].max().item(), "max_after": after[sel].max().item()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--strides", type=int, nargs="+", default=[2, 5, 10])
    parser.add_argument("--horizon", type=int, default=None)
    parser.add_argument("--streak", type=int, default=None)
    parser.add_argument("--hold", action="store_true",
                        help="round trips of the trajectories held at their last step (needs --streak)")
    parser.add_argument("--out", type=Path, default=None,
                        help="default: bench/results/coarsen_round_trip/<task>-<run>.json")
    args = parser.parse_args()
    if args.streak is not None and args.horizon is None:
        parser.error("--streak needs --horizon (the stop-rule cut comes before the fill)")
    if args.hold and args.streak is None:
        parser.error("--hold needs --streak: only the stop rule ends a held trajectory")
    cfg, trajs = load_run(args.run_dir)
    name = str(cfg.env.name)
    reward_fn = true_reward_fn(name, with_success=args.streak is not None)
    ids = torch.load(args.run_dir / "checkpoints" / "blocks.pt", weights_only=True)["block_ids"]
    out = args.out or ROOT / "bench" / "results" / "coarsen_round_trip" / f"{name}-{args.run_dir.name}.json"
    record = run_record(config={**{k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
                                "env": name})
    t0 = time.time()
    before = sample_true_return(trajs, reward_fn, horizon=args.horizon, streak=args.streak).double()
    record["strides"] = {}
    start = hold_last_step(trajs) if args.hold else trajs
    for stride in args.strides:
        trip = refine_trajectories(coarsen_trajectories(start, stride), stride, horizon=trajs.batch_size[1])
        after = sample_true_return(trip, reward_fn, horizon=args.horizon, streak=args.streak).double()
        record["strides"][str(stride)] = per_block(before, after, ids)
        summary = record["strides"][str(stride)]
        print(f"stride {stride}: " + " ".join(f"B{k} {v['before']:.0f}->{v['after']:.0f}"
                                             for k, v in summary.items()), flush=True)
    record["wall_time_s"] = round(time.time() - t0, 1)
    write_json(out, record)
    print(f"-> {out}")


if __name__ == "__main__":
    main()
