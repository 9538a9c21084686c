"""Session 48: does a lookahead change what Meta-World shooting reads? One run's generated samples that succeed
open loop (bench/results/open_loop_room_s45_reread.json) or shot greedily (bench/results/tracked_replay_s47/), shot
again with ``lookahead`` 1 (must reproduce session 47's numbers), 5 and 10 steps (candidates 4, noise 0.3, the run's
tracker fitted as bench/tracked_replay.py fits it: 4,000 steps, seed 0). Per sample: open-loop, shot stop-rule return
and success, hand deviation from the claimed path.

usage: python lookahead_check.py RUN OPEN_LOOP_JSON TRACKED_JSON OUT [L ...]   (venv active; one core)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from open_loop import load_flow  # noqa: E402

from torchrl_ftb.analysis import track_paths  # noqa: E402
from torchrl_ftb.analysis.replay import episode_jobs, replay_returns  # noqa: E402
from torchrl_ftb.analysis.tracking import _hand_deviation  # noqa: E402
from torchrl_ftb.policy import fit_path_tracker  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

run, ol_file, tr_file, out = Path(sys.argv[1]), sys.argv[2], sys.argv[3], Path(sys.argv[4])
looks = [int(x) for x in sys.argv[5:]] or [1, 5, 10]
ol = json.loads(Path(ol_file).read_text())["runs"][str(run)]["samples"]
tr = json.loads(Path(tr_file).read_text())["runs"][str(run)]["samples"]
cfg, data, meta, final, original, generated, rows = load_flow(run)
gen = final[generated]
if not (len(ol) == len(tr) == gen.batch_size[0]) or any(a["start_row"] != b["start_row"] for a, b in zip(ol, tr)):
    raise SystemExit("the open-loop and tracked files do not list this run's generated samples in one order")
pick = sorted({i for i, s in enumerate(ol) if s["replay_success"]} | {i for i, s in enumerate(tr) if s["tracked_success"]})
paths, actions = gen["observation"][pick], gen["action"][pick]
lengths = [int(n) for n in gen["mask"][pick].sum(-1).tolist()]
jobs = episode_jobs(meta, torch.tensor([tr[i]["start_row"] for i in pick]))
tracker = fit_path_tracker(data, steps=4000, seed=0, progress=False)
record = {**run_record(config={"run": str(run), "open_loop": ol_file, "tracked": tr_file, "samples": pick,
                               "candidates": 4, "noise": 0.3, "lookahead": looks, "horizon": 500}), "results": {}}
for look in looks:
    eps = track_paths(str(cfg.env.name), jobs, paths, lengths, tracker, seed=int(meta["seed"]),
                      max_steps=int(meta["max_steps"]), actions=actions, candidates=4, noise=0.3, lookahead=look)
    ret = replay_returns(eps, horizon=500)[:, 1]
    dev = _hand_deviation(eps, paths, lengths)
    record["results"][str(look)] = [
        {"sample": i, "start_row": tr[i]["start_row"], "claimed_stop_rule": tr[i]["claimed_stop_rule"],
         "open_loop_stop_rule": ol[i]["replayed_stop_rule"], "open_loop_success": ol[i]["replay_success"],
         "shot_s47_stop_rule": tr[i]["tracked_stop_rule"], "shot_stop_rule": float(r),
         "shot_success": bool(ep["success"].any()), "hand_deviation": float(d)}
        for i, r, ep, d in zip(pick, ret.tolist(), eps, dev)]
    best = max(record["results"][str(look)], key=lambda x: x["shot_stop_rule"])
    print(f"lookahead {look}: max shot {best['shot_stop_rule']:.0f} (sample {best['sample']}, open loop "
          f"{best['open_loop_stop_rule']:.0f}), successes {sum(x['shot_success'] for x in record['results'][str(look)])}"
          f"/{len(pick)}", flush=True)
    write_json(out, record)
print(f"-> {out}")
