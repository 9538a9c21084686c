"""session 47: Markdown rows of the shooting tracked readings (bench/tracked_replay.py --candidates 4).

usage: python3 shoot_rows.py LABEL=SHOOT_JSON[+IDM_JSON] ...
IDM_JSON (optional): a bench/tracked_replay.py file with the same run read by the tracker alone (its entry for
the same run path); its per-sample hand deviations are not needed. Files written before 0bf29e7 lack the tracker
alone's off-path bound: it is taken from IDM_JSON's top-k (the same tracker: data, seed and steps) when given.
"""
import json
import sys
from pathlib import Path


def entry(path: str) -> tuple[str, dict]:
    runs = json.loads(Path(path).read_text())["runs"]
    (run, e), = runs.items()
    return run, e


def idm_entry(path: str, run: str) -> dict:
    runs = json.loads(Path(path).read_text())["runs"]
    return next(v for k, v in runs.items() if Path(k).name == Path(run).name)


print("| run | top-k recorded / tracker alone / shooting (mean) | tracker alone: mean, max | shooting: mean | "
      "shooting: max | shooting: max on path (off path of generated) | generated: claimed → shot (successes) |")
print("|---|---|---|---|---|---|---|")
for arg in sys.argv[1:]:
    label, files = arg.split("=", 1)
    shoot, _, idm = files.partition("+")
    run, e = entry(shoot)
    f, t, g = e["fidelity"], e["tracked"], e["generated"]
    alone = idm_entry(idm, run) if idm else None
    bound = f.get("tracker_alone_hand_deviation_max", None if alone is None else alone["fidelity"]["hand_deviation_max"])
    alone_mean = f.get("tracker_alone_tracked_mean", None if alone is None else alone["fidelity"]["tracked_mean"])
    idm = (f"{alone['tracked']['true_return_mean_before']:,.0f} → {alone['tracked']['true_return_mean_after']:,.0f}, "
           f"{alone['tracked']['true_return_max_before']:,.0f} → {alone['tracked']['true_return_max_after']:,.0f}"
           if alone else "—")
    on = "—"
    if bound is not None:
        samples = e["samples"]
        kept = [s["tracked_stop_rule"] for s in samples if s["hand_deviation"] <= bound]
        best = max([t["true_return_max_before"]] + kept) if samples else t["true_return_max_before"]
        # the final set's originals are top-k trajectories: its on-path max is the larger of theirs and the kept samples'
        on = f"{t['true_return_max_before']:,.0f} → {best:,.0f} ({len(samples) - len(kept)} of {len(samples)})"
    print(f"| {label} | {f['recorded_mean']:,.0f} / {'—' if alone_mean is None else f'{alone_mean:,.0f}'} / "
          f"{f['tracked_mean']:,.0f} | {idm} | {t['true_return_mean_before']:,.0f} → {t['true_return_mean_after']:,.0f} | "
          f"{t['true_return_max_before']:,.0f} → **{t['true_return_max_after']:,.0f}** | {on} | "
          f"{g['claimed_stop_rule_mean']:,.0f} → {g['tracked_stop_rule_mean']:,.0f} ({g['tracked_success_rate']:.2f} of "
          f"{g['num_generated']}) |")
