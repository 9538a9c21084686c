"""Do a run's generated trajectories do in the simulator what their states say? Open-loop replays.

The bench form of :func:`torchrl_ftb.analysis.open_loop_improvement` (the recipe runs the same on its own
final set, ``analysis.open_loop``; see that module for the method): for finished FTB run directories on
generated Meta-World data, replay every generated trajectory of the final set (``checkpoints/flow.pt``)
from its nearest dataset start, open loop, and compare the simulator's returns with the ones its states
claim, original top-k -> final set. ``--no-hold`` stops each replay after the sample's last action
instead of holding still until the stop rule or the time limit.

Usage::

    python bench/open_loop.py --run-dirs RUN [RUN ...] --horizon 500 --out bench/results/open_loop.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from expert_headroom import load_metaworld_run  # noqa: E402
from flow_generated import require_finished_runs  # noqa: E402

from torchrl_ftb.analysis import nearest_start, open_loop_improvement, replay_returns  # noqa: E402,F401 (tests)
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def open_loop(run: Path, *, horizon: int, progress: bool, hold: bool = True) -> dict:
    """:func:`torchrl_ftb.analysis.open_loop_improvement` of a finished run directory's final set."""
    cfg, data, meta = load_metaworld_run(run)
    ckpt = torch.load(run / "checkpoints" / "flow.pt", weights_only=True)
    final = TensorDict(ckpt["trajectories"]["data"], batch_size=ckpt["trajectories"]["batch_size"])
    original = TensorDict(ckpt["original"]["data"], batch_size=ckpt["original"]["batch_size"])
    out = open_loop_improvement(final, original, ckpt["source_step"] > 0, data, meta, task=str(cfg.env.name),
                                horizon=horizon, original_rows=ckpt.get("original_indices"), hold=hold,
                                progress=progress)
    return {"env": str(cfg.env.name), "seed": int(cfg.seed), "top_k": int(original.batch_size[0]),
            "flow_filter": str(cfg.flow.get("filter", "score_model")),
            "diffuser_strength": float(cfg.diffuser.get("strength", 1.0)), **out}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--horizon", type=int, default=500, help="the stop-rule return's horizon (Meta-World: 500)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "open_loop.json")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-hold", action="store_true",
                        help="stop each replay after the sample's last action (default: the hand then holds still, "
                             "zero actions, until the stop rule or the time limit)")
    args = parser.parse_args()
    require_finished_runs(parser, args.run_dirs)
    record = {**run_record(config={"run_dirs": [str(r) for r in args.run_dirs], "horizon": args.horizon,
                                   "hold": not args.no_hold}), "runs": {}}
    for run in args.run_dirs:
        entry = record["runs"][str(run)] = open_loop(run, horizon=args.horizon, progress=not args.no_progress,
                                                     hold=not args.no_hold)
        for name, v in entry["improvement"].items():
            c, r = v["claimed"], v["replayed"]
            print(f"{entry['env']} seed {entry['seed']} {name}: mean {c['true_return_mean_before']:.0f} -> "
                  f"{c['true_return_mean_after']:.0f} claimed / {r['true_return_mean_after']:.0f} replayed; max "
                  f"{c['true_return_max_before']:.0f} -> {c['true_return_max_after']:.0f} claimed / "
                  f"{r['true_return_max_after']:.0f} replayed")
        write_json(args.out, record)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
