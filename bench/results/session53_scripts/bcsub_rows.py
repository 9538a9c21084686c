"""Session 53: Markdown rows of bc_subsets.py files: per subset, the trajectories BC saw and the policy's success rate
and return over the 50 evaluation episodes.

usage: python3 bcsub_rows.py LABEL=FILE.json [...]
"""
import json
import sys

NAMES = {"topk": "top-k alone", "final": "final set (the recipe's BC)", "topk+on_path": "top-k + on-path generated",
         "topk+off_path": "top-k + off-path generated", "on_path": "on-path generated alone"}
print("| flowed set | BC on | trajectories | policy success | policy return, mean |")
print("|" + "---|" * 5)
for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    rec = json.load(open(path))
    for name, r in rec["subsets"].items():
        print(f"| {label} ({rec['off_path']} of {rec['generated']} generated off path) | {NAMES[name]} | "
              f"{r['trajectories']} | {r['success_rate']:.2f} | {r['return_mean']:.0f} |")
