"""Session 41: one Markdown row per imported recipe cell (bench/table1.py --import-run): the flow's final set against
the top-k (plain, stop-rule, open-loop replay), the accepted samples and the policy.
usage: python recipe_rows.py LABEL=CELL.json ..."""
import json
import sys

print("| run | diffuser | accepted (generated share of final) | plain mean | plain max | stop-rule mean | stop-rule max "
      "| replayed mean | replayed max | generated: claimed → replayed (successes) | policy success |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    d = json.load(open(path))
    m = d["metrics"]
    f, a = m["flow"], m.get("analysis", {})
    ol = a.get("open_loop", {})

    def pair(before, after, fmt="{:.0f}"):
        return f"{fmt.format(before)} → {fmt.format(after)}"

    row = [label, f"{m['diffuser'].get('steps', '?')} steps",
           f"{f['num_generated_accepted']:.0f} ({f['fraction_generated_in_final']:.3g})",
           pair(f["true_return_mean_before"], f["true_return_mean_after"]),
           pair(f["true_return_max_before"], f["true_return_max_after"]),
           pair(f["true_return_filled_stop_rule_mean_before"], f["true_return_filled_stop_rule_mean_after"]),
           pair(f["true_return_filled_stop_rule_max_before"], f["true_return_filled_stop_rule_max_after"])]
    if ol:
        rep = ol["improvement"]["stop_rule_500"]["replayed"]
        row += [pair(rep["true_return_mean_before"], rep["true_return_mean_after"]),
                pair(rep["true_return_max_before"], rep["true_return_max_after"]),
                f"{ol['claimed_stop_rule_mean_generated']:.0f} → {ol['replayed_stop_rule_mean_generated']:.0f}"
                f" ({ol['replay_success_rate']:.2g})" if ol.get("num_generated") else "— (none generated)"]
    else:
        row += ["—"] * 3
    row.append(f"{d['score']:.2f}")
    print("| " + " | ".join(row) + " |")
