"""Table-2 harness: FTB as data augmentation for offline RL (paper §4.4) vs SYNTHETIC vs none.

Cells are ``recipes/baselines.py method=<td3bc|iql> augmentation.kind=<none|synthetic|ftb>``
runs through the Table-1 harness (``bench/table1.run_cell``: resumable, a cell whose JSON
exists is skipped, JSON with command / config / commit / machine / wall time / score). The two
methods of one seed share one supplement per kind (``augmentation.cache_dir``), as the paper
augments a dataset once and trains both algorithms on it.

    python bench/table2.py --tasks hopper-medium-replay --seeds 0,1,2 \\
        --extra eval.max_steps=1000                     # run the cells
    python bench/table2.py --summary                    # print the Markdown tables (per kind; paired by seed)

Cells: ``bench/results/table2/<kind>/<method>__<task>__return__seed<k>.json``.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import statistics
import sys
from pathlib import Path
from typing import Iterable

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table1 import ROOT, _csv, cell_path, load_cells, run_cell  # noqa: E402

RESULTS_DIR = ROOT / "bench" / "results" / "table2"
KINDS = ("none", "synthetic", "ftb")
METHODS = ("td3bc", "iql")
#: Paper, Table 2 (D4RL v2, 5 seeds): (Original, SYNTHETIC, TrajDiffuser/FTB) per method
PAPER_TABLE2 = {
    "halfcheetah-medium-replay-v2": {"td3bc": (44.8, 45.4, 44.7), "iql": (44.5, 46.7, 44.1)},
    "halfcheetah-medium-expert-v2": {"td3bc": (90.8, 85.9, 94.7), "iql": (94.7, 93.6, 92.6)},
    "hopper-medium-replay-v2": {"td3bc": (64.4, 54.0, 80.2), "iql": (97.4, 102.8, 100.4)},
    "hopper-medium-expert-v2": {"td3bc": (101.2, 102.5, 101.5), "iql": (107.4, 97.5, 111.2)},
    "walker2d-medium-replay-v2": {"td3bc": (85.6, 91.9, 93.6), "iql": (82.2, 90.2, 81.6)},
    "walker2d-medium-expert-v2": {"td3bc": (110.0, 110.1, 110.2), "iql": (111.7, 111.8, 111.3)},
}


def summary(results_dir: Path) -> str:
    """Markdown: per task and method, mean ± std (n) of each kind, and the supplement's returns."""
    rows = ["| task | method | none | SYNTHETIC | FTB | paper (D4RL v2): none / SYNTHETIC / FTB | supplement true return "
            "(generated) → replayed open loop → tracked closed loop [dynamics error] per seed: SYNTHETIC ; FTB |", "|---|---|---|---|---|---|---|"]
    cells = {kind: load_cells(results_dir / kind) for kind in KINDS}
    tasks = sorted({c["env"] for kind in KINDS for c in cells[kind]})
    for task in tasks:
        for method in METHODS:
            out, sup = [], []
            for kind in KINDS:
                scores = [c["score"] for c in cells[kind] if c["env"] == task and c["method"] == method]
                if not scores:
                    out.append("—")
                else:
                    sd = statistics.pstdev(scores) if len(scores) > 1 else 0.0
                    out.append(f"{statistics.mean(scores):.1f} ± {sd:.1f} ({len(scores)})")
                if kind != "none":
                    aug = [c["metrics"].get("augmentation", {}) for c in cells[kind]
                           if c["env"] == task and c["method"] == method]
                    vals = [(a["true_return_mean"], a.get("generated_return_mean"),
                             [a.get(f"{r}_return_mean") for r in ("replayed", "tracked")], a.get("dynamics_error_mean"))
                            for a in aug if a.get("true_return_mean") is not None]
                    sup.append(" / ".join(f"{t:.0f} ({g:.0f})" + "".join(f" → {r:.0f}" for r in rs if r is not None)
                                          + (f" [{e:.2f}]" if e is not None else "") for t, g, rs, e in vals) or "—")
            paper = PAPER_TABLE2.get(re.sub(r"-v\d+$", "", task) + "-v2", {}).get(method)
            paper_cell = " / ".join(f"{v:.1f}" for v in paper) if paper else "—"
            rows.append(f"| {task} | {method} | " + " | ".join(out) + f" | {paper_cell} | " + " ; ".join(sup) + " |")
    return "\n".join(rows)


def sign_flip_p(diffs: list[float]) -> float:
    """Two-sided exact paired randomisation test of "mean difference 0": the share of the ``2^n`` sign
    assignments of ``diffs`` whose mean is at least as far from 0 as the observed one (scipy's
    ``permutation_test`` with ``permutation_type="samples"``, all assignments). With the few seeds a
    Table-2 cell has, the smallest possible p is ``2 / 2^n`` (n = 5: 0.0625), which the table shows.

    Example:
        >>> sign_flip_p([1.0, 2.0, 3.0])  # only all-plus and all-minus reach |mean| 2
        0.25
    """
    import numpy as np
    from scipy.stats import permutation_test

    if not 1 <= len(diffs) <= 20:
        raise ValueError(f"sign_flip_p: needs 1 to 20 paired differences (exact enumeration), got {len(diffs)}")
    if len(diffs) == 1:  # both signs reach |mean|; scipy wants two or more observations
        return 1.0
    result = permutation_test((np.asarray(diffs, dtype=float),), np.mean, permutation_type="samples",
                              n_resamples=np.inf, alternative="two-sided")
    return float(result.pvalue)


#: what :func:`paired` compares, (a, b): a − b on the seeds both have
PAIRS = (("synthetic", "none"), ("ftb", "none"), ("ftb", "synthetic"))


def paired(results_dir: Path) -> str:
    """Markdown: each augmented kind against ``none``, and FTB against SYNTHETIC (:data:`PAIRS`), on the seeds
    both have, per task and method -- the per-seed differences, their mean ± standard error, how many are
    positive, and :func:`sign_flip_p`."""
    cells = {kind: {(c["env"], c["method"], int(c["seed"])): float(c["score"]) for c in load_cells(results_dir / kind)}
             for kind in KINDS}
    rows = ["| task | method | comparison | seeds | per seed | mean ± s.e. | higher | p (sign flip, two-sided) |",
            "|---|---|---|---|---|---|---|---|"]
    for task, method in sorted({key[:2] for kind in KINDS for key in cells[kind]}):
        for a, b in PAIRS:
            seeds = sorted(s for (t, m, s) in cells[a] if (t, m) == (task, method) and (t, m, s) in cells[b])
            if not seeds:
                continue
            diffs = [cells[a][(task, method, s)] - cells[b][(task, method, s)] for s in seeds]
            mean = statistics.mean(diffs)
            se = statistics.stdev(diffs) / math.sqrt(len(diffs)) if len(diffs) > 1 else float("nan")
            rows.append(f"| {task} | {method} | {a} − {b} | {', '.join(map(str, seeds))} | "
                        + " / ".join(f"{d:+.2f}" for d in diffs)
                        + f" | {mean:+.2f} ± {se:.2f} | {sum(d > 0 for d in diffs)}/{len(diffs)} | "
                          f"{sign_flip_p(diffs):.3f} |")
    return "\n".join(rows)


def main(argv: Iterable[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", type=_csv, default=["hopper-medium-replay"])
    parser.add_argument("--seeds", type=_csv, default=["0"])
    parser.add_argument("--methods", type=_csv, default=list(METHODS))
    parser.add_argument("--kinds", type=_csv, default=list(KINDS))
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--extra", nargs="*", default=[], help="extra hydra overrides for every cell")
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "outputs" / "table2")
    parser.add_argument("--summary", action="store_true", help="print the Markdown table of the finished cells")
    args = parser.parse_args(list(argv) if argv is not None else None)
    if args.summary:
        print(summary(args.results_dir))
        print()
        print(paired(args.results_dir))
        return 0
    failures = 0
    for task in args.tasks:
        for seed in map(int, args.seeds):
            for kind in args.kinds:
                if kind not in KINDS:
                    parser.error(f"unknown kind {kind!r}; choose from {KINDS}")
                cache = args.runs_dir / "supplements" / task / f"seed{seed}"
                extra = [f"augmentation.kind={kind}", f"augmentation.cache_dir={cache}", *args.extra]
                for method in args.methods:
                    record = run_cell(method, task, seed, teacher="return", preset=args.preset, extra=extra,
                                      threads=args.threads, runs_dir=args.runs_dir / kind,
                                      results_dir=args.results_dir / kind)
                    failures += record is None
                    if record is not None:
                        print(json.dumps({"cell": cell_path(args.results_dir / kind, method, task, "return", seed).name,
                                          "score": record["score"]}), flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
