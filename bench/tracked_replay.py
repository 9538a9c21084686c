"""Are a run's generated state paths reachable? Closed-loop tracked replays, top-k vs final set.

The bench form of :func:`torchrl_ftb.analysis.tracked_improvement` (see :mod:`torchrl_ftb.analysis.tracking`
for the method): for finished FTB run directories on generated Meta-World data, fit a goal-conditioned
inverse-dynamics tracker on the run's dataset, then track every original top-k trajectory and every generated
trajectory of the final set (``checkpoints/flow.pt``) in the simulator from its (nearest) dataset start,
and compare top-k -> final set with both sides read the same way. By default (since session 52) each step shoots:
the path's own action, the tracker's and perturbations are tried in the simulator (``--candidates 4``, exact on
recorded paths) and every generated path is read 4 times (``--readers``); ``--candidates 1``: the tracker alone
(the readings of sessions 31-46). Open-loop replays of the same samples:
``bench/open_loop.py``.

Usage::

    python bench/tracked_replay.py --run-dirs RUN [RUN ...] --horizon 500 --out bench/results/tracked.json
        # shooting with 4 candidates (exact on the top-k), each generated path's mean of 4 readings
    python bench/tracked_replay.py --run-dirs RUN --lookahead 5 --out F   # each candidate scored 5 steps ahead
    python bench/tracked_replay.py --run-dirs RUN --candidates 1 --out F   # the inverse-dynamics tracker alone
    python bench/tracked_replay.py --summarize bench/results/tracked_replay_s31/*.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_generated import measure_runs, runs_from_args  # noqa: E402
from open_loop import load_flow  # noqa: E402

from torchrl_ftb.analysis import check_readers, tracked_improvement  # noqa: E402
from torchrl_ftb.policy import fit_path_tracker  # noqa: E402


def tracked(run: Path, *, horizon: int, tracker_steps: int, seed: int, progress: bool, candidates: int = 4,
            noise: float = 0.3, lookahead: int = 1, readers: int | None = None) -> dict:
    """:func:`torchrl_ftb.analysis.tracked_improvement` of a finished run directory's final set (``candidates``
    > 1: shooting in the simulator, :func:`torchrl_ftb.analysis.track_paths`, scored over ``lookahead`` steps;
    ``readers`` None: 4 readings with shooting, 1 without; the recipe's ``analysis.tracked`` defaults)."""
    cfg, data, meta, final, original, generated, rows = load_flow(run)
    tracker = fit_path_tracker(data, steps=tracker_steps, seed=seed, progress=progress)
    out = tracked_improvement(final, original, generated, data, meta, task=str(cfg.env.name), horizon=horizon,
                              tracker=tracker, original_rows=rows, candidates=candidates, noise=noise,
                              lookahead=lookahead, readers=readers, progress=progress)
    return {"env": str(cfg.env.name), "seed": int(cfg.seed), "top_k": int(original.batch_size[0]),
            "inpaint_start": bool(cfg.diffuser.get("inpaint_start", False)), **out}


SUMMARY_HEADER = ("| run | task, seed | reading | samples start | generated in final set | tracker on the top-k: recorded → tracked "
                  "mean (hand off path, median) | generated: claimed → tracked (hand off path, median; tracks that "
                  "succeed) | mean: top-k → final, claimed / **tracked** | max: top-k → final, claimed / **tracked** | "
                  "off path (of generated): max → tracked max on path |")


def on_path(entry: dict) -> str:
    """``"<off path> (of <generated>): <top-k max> → <final max without them>"``; ``—`` for files written before
    the bench recorded it (session 32)."""
    if "tracked_on_path" not in entry:
        return "—"
    t, g = entry["tracked_on_path"], entry["generated"]
    return (f"{g['off_path']} (of {g['num_generated']}): {t['true_return_max_before']:.0f} → "
            f"{t['true_return_max_after']:.0f}")


def reading(entry: dict) -> str:
    """How the file read its paths: ``"tracker"`` (the inverse-dynamics tracker alone; files before session 47
    record nothing) or ``"shot C×R"`` (C candidates, each generated path read R times, ``, L-step`` lookahead)."""
    shot = entry.get("shooting") or {}
    if int(shot.get("candidates", 1)) < 2:
        return "tracker"
    look = int(shot.get("lookahead", 1))
    return f"shot {int(shot['candidates'])}×{int(shot.get('readers', 1))}" + (f", {look}-step" if look > 1 else "")


def summarize(paths: list[Path]) -> str:
    """One Markdown row (:data:`SUMMARY_HEADER`) per run of this bench's results files."""
    rows = [SUMMARY_HEADER, "|" + "---|" * (SUMMARY_HEADER.count(" | ") + 1)]
    cm = lambda v: "—" if v is None else f"{100 * v:.1f} cm"  # noqa: E731
    for path in paths:
        for run, e in json.loads(Path(path).read_text())["runs"].items():
            t, c, f, g = e["tracked"], e["claimed"], e["fidelity"], e["generated"]
            n = g["num_generated"]
            gen = (f"{g['claimed_stop_rule_mean']:.0f} → {g['tracked_stop_rule_mean']:.0f} ({cm(g['hand_deviation_median'])}; "
                   f"{100 * g['tracked_success_rate']:.0f}%)" if n else "—")
            rows.append(f"| {Path(run).parent.parent.name if Path(run).name.startswith('seed') else Path(run).name} | "
                        f"{e['env']} s{e['seed']} | {reading(e)} | {'held' if e['inpaint_start'] else 'anywhere'} | {n} | "
                        f"{f['recorded_mean']:.0f} → {f['tracked_mean']:.0f} ({cm(f['hand_deviation_median'])}) | {gen} | "
                        f"{c['true_return_mean_before']:.0f} → {c['true_return_mean_after']:.0f} / "
                        f"**{t['true_return_mean_before']:.0f} → {t['true_return_mean_after']:.0f}** | "
                        f"{c['true_return_max_before']:.0f} → {c['true_return_max_after']:.0f} / "
                        f"**{t['true_return_max_before']:.0f} → {t['true_return_max_after']:.0f}** | {on_path(e)} |")
    return "\n".join(rows)


def describe(run: Path, e: dict) -> str:
    """One printed line per measured run."""
    t, c, f, g = e["tracked"], e["claimed"], e["fidelity"], e["generated"]
    return (f"{e['env']} seed {e['seed']}: tracked mean {t['true_return_mean_before']:.0f} -> "
            f"{t['true_return_mean_after']:.0f}, max {t['true_return_max_before']:.0f} -> {t['true_return_max_after']:.0f} "
            f"(claimed mean {c['true_return_mean_before']:.0f} -> {c['true_return_mean_after']:.0f}); fidelity: "
            f"top-k recorded {f['recorded_mean']:.0f} tracked {f['tracked_mean']:.0f}; {g['num_generated']} generated")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path)
    parser.add_argument("--summarize", nargs="+", type=Path, help="print the Markdown table of these results files")
    parser.add_argument("--horizon", type=int, default=500, help="the stop-rule return's horizon (Meta-World: 500)")
    parser.add_argument("--tracker-steps", type=int, default=4000, help="Adam steps fitting the tracker")
    parser.add_argument("--seed", type=int, default=0, help="the tracker's seed")
    parser.add_argument("--candidates", type=int, default=4,
                        help="actions tried per step: more than 1 (default 4) = shooting in the simulator (the path's "
                             "own action, the tracker's, perturbations), exact on recorded paths; 1 = the tracker alone")
    parser.add_argument("--noise", type=float, default=0.3, help="std of the shooting's perturbations")
    parser.add_argument("--lookahead", type=int, default=1,
                        help="shooting: steps each candidate is scored over (the path's own next actions shifted by "
                             "its offset); 1 = greedy")
    parser.add_argument("--readers", type=int, default=None,
                        help="shooting: read each generated path this many times, each with other perturbations, "
                             "and take the means (a property of the path, not of one reading's draws); default 4 "
                             "with shooting, 1 with the tracker alone")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "tracked_replay.json")
    parser.add_argument("--no-progress", action="store_true")
    args = runs_from_args(parser, summarize)
    if args is None:
        return
    if args.candidates < 1:
        parser.error(f"--candidates {args.candidates}: must be >= 1 (1: the tracker alone)")
    try:  # before the tracker is fitted
        args.readers = check_readers(args.readers, args.candidates)
    except ValueError as err:
        parser.error(f"--readers {args.readers} with --candidates {args.candidates}: {err}")
    measure_runs(args.run_dirs, args.out, {"horizon": args.horizon, "tracker_steps": args.tracker_steps,
                                           "seed": args.seed, "candidates": args.candidates, "noise": args.noise,
                                           "lookahead": args.lookahead, "readers": args.readers},
                 lambda run: tracked(run, horizon=args.horizon, tracker_steps=args.tracker_steps, seed=args.seed,
                                     progress=not args.no_progress, candidates=args.candidates, noise=args.noise,
                                     lookahead=args.lookahead, readers=args.readers),
                 describe)


if __name__ == "__main__":
    main()
