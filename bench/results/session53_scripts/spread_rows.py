"""Session 53: one Markdown row per flowed set: the BC policy's success rate for BC seeds 0-3 (bc_spread.sh copies,
/work/runs/room_s53/<run>_bcseed<K>) and the run's own BC seed (its seed, 4), with their mean and range.

usage: python3 spread_rows.py LABEL=RUN_DIR[=TAG] [...]   (TAG: bc_spread.sh's TAG; then seed 4 is
<run>_bcseed4_<TAG> too)
"""
import json
import sys
from pathlib import Path

print("| flowed set | BC seed 0 | 1 | 2 | 3 | 4 (the run's) | mean | range |")
print("|" + "---|" * 8)
for arg in sys.argv[1:]:
    label, run, *tag = arg.split("=")
    run, suffix = Path(run), f"_{tag[0]}" if tag else ""
    seeds = range(5) if tag else range(4)
    rates = [json.loads((Path("/work/runs/room_s53") / f"{run.name}_bcseed{k}{suffix}" / "metrics.json").read_text())
             ["eval"]["success_rate"] for k in seeds]
    if not tag:  # seed 4 is the run's own BC
        rates.append(json.loads((run / "metrics.json").read_text())["eval"]["success_rate"])
    print(f"| {label} | " + " | ".join(f"{r:.2f}" for r in rates)
          + f" | {sum(rates) / len(rates):.2f} | {min(rates):.2f}–{max(rates):.2f} |")
