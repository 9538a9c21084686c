"""Session 46: one Markdown row per imported recipe cell with the tracked reading (analysis.tracked=true): the final
set against the top-k at the stop rule (horizon 500), claimed by the states, replayed open loop and tracked in closed
loop, the tracker's fidelity on the top-k and the policy.
usage: python tracked_rows.py LABEL=CELL.json ..."""
import json
import sys


def pair(r: dict, stat: str) -> str:
    return f"{r[f'true_return_{stat}_before']:,.0f} → {r[f'true_return_{stat}_after']:,.0f}"


print("| run | claimed mean | claimed max | replayed mean | replayed max | tracked mean | tracked max "
      "| tracked max on path | top-k recorded → tracked (mean) | generated tracked successes | policy success |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    d = json.load(open(path))
    a = d["metrics"]["analysis"]
    tr, rep = a["tracked"], a["open_loop"]["improvement"]["stop_rule_500"]["replayed"]
    fid, gen = tr["fidelity"], tr["generated"]
    row = [label, pair(tr["claimed"], "mean"), pair(tr["claimed"], "max"), pair(rep, "mean"), pair(rep, "max"),
           pair(tr["tracked"], "mean"), pair(tr["tracked"], "max"), pair(tr["tracked_on_path"], "max"),
           f"{fid['recorded_mean']:,.0f} → {fid['tracked_mean']:,.0f}",
           f"{gen['tracked_success_rate']:.2f} of {gen['num_generated']}" if gen["num_generated"] else "— (none)",
           f"{d['score']:.2f}"]
    print("| " + " | ".join(row) + " |")
