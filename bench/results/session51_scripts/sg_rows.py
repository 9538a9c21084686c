"""Session 51: one Markdown row per run, its recipe numbers beside its readers reading (readers.sh: shooting, each
generated path read 4 times; a path's numbers are its means, off path if any reading leaves the claimed hand further
than the tracker alone leaves a top-k path).

usage: python3 sg_rows.py LABEL=RUN_DIR=READERS.json [...]
(session 54: RUN_DIR "-" takes the claimed numbers from the reading itself and leaves the policy empty, for a run whose
directory is gone)
Columns: the flow's claimed stop-rule mean and max, top-k -> final set (metrics.json); generated samples in the final
set (off path); executed on path, mean and max (top-k read once: shooting reproduces it); on-path generated paths above
the top-k's best in every reading; generated paths that succeed in every reading; the BC policy's success rate.
"""
import json
import sys


def row(label: str, run_dir: str | None, path: str) -> str:
    """One row; ``run_dir`` None: the claimed numbers from the reading itself and no policy (session 54)."""
    run = next(iter(json.load(open(path))["runs"].values()))
    k = "true_return_filled_stop_rule"
    if run_dir is None:
        flow = {f"{k}_{x}": run["claimed"][f"true_return_{x}"]
                for x in ("mean_before", "mean_after", "max_before", "max_after")}
        policy = None
    else:
        metrics = json.load(open(f"{run_dir}/metrics.json"))
        flow, policy = metrics["flow"], metrics["eval"]["success_rate"]
    on, g, samples = run["tracked_on_path"], run["generated"], run["samples"]
    bound = run["fidelity"]["tracker_alone_hand_deviation_max"]
    best = on["true_return_max_before"]
    on_path = [s for s in samples if max(s["hand_deviation_per_reader"]) <= bound]
    assert len(on_path) == g["num_generated"] - g["off_path"], (len(on_path), g)
    above = [s for s in on_path if min(s["tracked_stop_rule_per_reader"]) > best]
    lowest = max((min(s["tracked_stop_rule_per_reader"]) for s in above), default=None)
    cells = [label,
             f"{flow[f'{k}_mean_before']:,.0f} → {flow[f'{k}_mean_after']:,.0f}",
             f"{flow[f'{k}_max_before']:,.0f} → {flow[f'{k}_max_after']:,.0f}",
             f"{g['num_generated']} ({g['off_path']})",
             f"{on['true_return_mean_before']:,.0f} → {on['true_return_mean_after']:,.0f}",
             f"{best:,.0f} → **{on['true_return_max_after']:,.0f}**",
             f"{len(above)}" + (f" (best lowest reading {lowest:,.0f})" if above else ""),
             f"{sum(s['tracked_success'] == 1 for s in samples)} / {g['num_generated']}",
             "—" if policy is None else f"{policy:.2f}"]
    return "| " + " | ".join(cells) + " |"


HEADER = ("| run | claimed mean, top-k → final | claimed max | generated in final set (off path) | executed on path, mean"
          " | executed on path, max | on-path paths above the top-k's best in every reading | generated paths succeeding"
          " in every reading | policy success |\n|" + "---|" * 9)

if __name__ == "__main__":
    print(HEADER)
    for arg in sys.argv[1:]:
        label, run_dir, path = arg.split("=", 2)
        print(row(label, None if run_dir == "-" else run_dir, path))
