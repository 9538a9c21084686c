"""Session 53: Markdown rows of ensemble_guide.py files: per strength, objective and lambda, the top block's samples'
claimed stop-rule return (mean, max; conditions' beside), share above their own condition, and their normalised
s_psi and ensemble-mean scores; then each file's Spearman line.

usage: python3 ensemble_rows.py LABEL=FILE.json [...]
"""
import json
import sys

print("| run | strength | guide | λ | claimed return, mean (conditions') | max (conditions') | above own condition |"
      " ŝ (s_ψ) | ŝ (ensemble mean) |")
print("|" + "---|" * 9)
notes = []
for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    rec = json.load(open(path))
    for r in rec["rows"]:
        print(f"| {label} | {r['strength']:g} | {r['objective']} | {r['lambda']:g} | {r['true_mean']:,.0f} "
              f"({r['conditions_true_mean']:,.0f}) | {r['true_max']:,.0f} ({r['conditions_true_max']:,.0f}) | "
              f"{r['above_own_condition']:.2f} | {r['single_score_norm']:.2f} | {r['ensemble_score_norm']:.2f} |")
    d = rec["data"]
    notes.append(f"{label}: Spearman with the true return on the dataset, s_ψ {d['spearman_single']:.2f}, ensemble mean "
                 f"{d['spearman_ensemble_mean']:.2f}, pessimistic bound {d['spearman_ensemble_lcb']:.2f}")
print()
for n in notes:
    print(f"- {n}")
