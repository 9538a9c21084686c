"""Session 51: one Markdown row per conditioning-bench file (sg_sweep.sh): the top block's conditions and their samples.

usage: python3 sweep_rows.py LABEL=FILE.json [...]
Columns: lambda; s_psi score, conditions -> samples, mean and max; stop-rule true return read off the states, conditions
-> samples, mean and max; share of samples above their own condition's true return; trajectory gap to the own
condition (0: a copy; two data trajectories ~2).
"""
import json
import sys

print("| run | λ | score: conditions → samples, mean | max | true return (claimed): conditions → samples, mean | max"
      " | samples above their condition | gap to own condition |")
print("|" + "---|" * 8)
for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    rec = json.load(open(path))
    ev = rec["evaluations"][-1]
    per = ev["per_condition_block"]
    top = per[str(max(int(k) for k in per))]
    print(f"| {label} | {rec['config']['score_guidance']:g} | {top['condition_score']:,.0f} → {top['sample_score']:,.0f}"
          f" | {top['condition_score_max']:,.0f} → {top['sample_score_max']:,.0f}"
          f" | {top['condition_true_return']:,.0f} → {top['sample_true_return']:,.0f}"
          f" | {top['condition_true_return_max']:,.0f} → **{top['sample_true_return_max']:,.0f}**"
          f" | {top['samples_above_condition']:.2f} | {ev['trajectory_gap']['own']:.2f} |")
