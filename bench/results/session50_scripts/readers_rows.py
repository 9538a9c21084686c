"""Session 50: one Markdown row per readers reading (bench/tracked_replay.py --readers R; session 49's readers.sh).

usage: python3 readers_rows.py LABEL=FILE.json [LABEL=FILE.json ...]
Columns: generated samples in the final set (off path), the final set's mean and max (each path's mean over the
readings; the top-k read once), the max without off-path samples, each reading's own max, samples succeeding in at
least one / every reading, and the best path: its readings, claimed return and mean hand deviation.
"""
import json
import sys


def row(label: str, path: str) -> str:
    run = next(iter(json.load(open(path))["runs"].values()))
    t, on, g, samples = run["tracked"], run["tracked_on_path"], run["generated"], run["samples"]
    readers = len(run["tracked_per_reader"])
    best = max(samples, key=lambda s: s["tracked_stop_rule"])
    cells = [label, f"{g['num_generated']} ({g['off_path']})",
             f"{t['true_return_mean_before']:,.0f} → {t['true_return_mean_after']:,.0f}",
             f"{t['true_return_max_before']:,.0f} → **{t['true_return_max_after']:,.0f}**",
             f"{on['true_return_max_before']:,.0f} → {on['true_return_max_after']:,.0f}",
             " / ".join(f"{r['true_return_max_after']:,.0f}" for r in run["tracked_per_reader"]),
             f"{sum(s['tracked_success'] > 0 for s in samples)} / {sum(s['tracked_success'] == 1 for s in samples)}",
             f"{best['tracked_stop_rule']:,.0f} ({' / '.join(f'{v:,.0f}' for v in best['tracked_stop_rule_per_reader'])};"
             f" claimed {best['claimed_stop_rule']:,.0f}; {100 * best['hand_deviation']:.1f} cm)"]
    assert readers == len(best["tracked_stop_rule_per_reader"])
    return "| " + " | ".join(cells) + " |"


print("| run | generated in final set (off path) | final set mean, path means | final set max, path means"
      " | max without off-path samples | each reading's own max | samples succeeding in ≥ 1 / all readings"
      " | best path: mean (readings; claimed; hand deviation) |")
print("|" + "---|" * 8)
for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    print(row(label, path))
