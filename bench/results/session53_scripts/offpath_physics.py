"""Session 53: what tells a generated Meta-World path the shooting readers leave (off path) from one they follow?
For each (run, readers file) pair: every generated trajectory of the run's final set, its off-path flag (any reading's
hand deviation above the tracker-alone bound, as bench/tracked_replay.py counts it) and a set of per-trajectory
features read off the sample alone: the three physics proxies of bench/flow_generated.py (frame-stack error,
hand-model error, contactless object path), the largest hand step, the closest hand-object approach, the share of
valid steps whose hand / object lies outside the original top-k's box (per axis, +-1 cm), the object's total path,
the mean and largest |action|, the share of clipped action entries (|a| > 1), and the start's distance (max-abs) to the nearest
original top-k start. Reports per feature the off-path and on-path medians and the AUC (the chance an off-path path's value
exceeds an on-path one's; 0.5 = no signal, ties count half).

usage: python bench/results/session53_scripts/offpath_physics.py OUT.json RUN_DIR=READERS.json [...]
"""
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from flow_generated import generated_rows, load_flow_sets, physics_reference  # noqa: E402

from torchrl_ftb.analysis.replay import nearest_start  # noqa: E402
from torchrl_ftb.envs import metaworld_closest_approach, metaworld_max_hand_step  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def outside_box(x: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor, ref_mask: torch.Tensor) -> torch.Tensor:
    """``[N]`` share of valid steps whose point ``x[..., 3]`` lies outside ``ref``'s per-axis box +- 1 cm."""
    pts = ref[ref_mask.bool()]
    lo, hi = pts.amin(0) - 0.01, pts.amax(0) + 0.01
    out = ((x < lo) | (x > hi)).any(-1) & mask.bool()
    return out.sum(-1) / mask.sum(-1).clamp_min(1)


def features(final, original, generated, ckpt, data_first) -> dict[str, torch.Tensor]:
    gen = final[generated]
    obs, act, mask = gen["observation"].double(), gen["action"].double(), gen["mask"].bool()
    ref = physics_reference(original, contact_quantile=0.99)
    rows = generated_rows(ckpt, final, generated, ref)
    out = {k: torch.tensor([r[k] for r in rows], dtype=torch.float64)
           for k in ("frame_stack_error_m", "hand_model_error_m", "contactless_object_path_m")}
    out["max_hand_step_m"] = metaworld_max_hand_step(gen).double()
    out["closest_approach_m"] = metaworld_closest_approach(gen).double()
    o_obs, o_mask = original["observation"].double(), original["mask"].bool()
    out["hand_outside_box"] = outside_box(obs[..., 0:3], o_obs[..., 0:3], mask, o_mask)
    out["object_outside_box"] = outside_box(obs[..., 4:7], o_obs[..., 4:7], mask, o_mask)
    pair = mask[:, 1:] & mask[:, :-1]
    out["object_path_m"] = ((obs[:, 1:, 4:7] - obs[:, :-1, 4:7]).norm(dim=-1) * pair).sum(-1)
    a = act.abs()
    out["action_mean_abs"] = (a.mean(-1) * mask).sum(-1) / mask.sum(-1)
    out["action_max_abs"] = torch.where(mask[..., None], a, 0).amax((-1, -2))
    out["action_clipped_share"] = ((a > 1).double().mean(-1) * mask).sum(-1) / mask.sum(-1)
    out["start_distance"] = nearest_start(gen["observation"][:, 0].float(), data_first)[1].double()
    out["length"] = mask.sum(-1).double()
    return out


def auc(pos: torch.Tensor, neg: torch.Tensor) -> float | None:
    if pos.numel() == 0 or neg.numel() == 0:
        return None
    d = pos[:, None] - neg[None, :]
    return float(((d > 0).double() + 0.5 * (d == 0).double()).mean())


def main() -> None:
    out_path = Path(sys.argv[1])
    torch.set_num_threads(1)
    record = {**run_record(config={"pairs": sys.argv[2:]}), "runs": {}}
    for pair in sys.argv[2:]:
        run, readers_file = (Path(x) for x in pair.split("="))
        readers = json.loads(readers_file.read_text())
        entry = readers["runs"][str(run)] if str(run) in readers["runs"] else next(iter(readers["runs"].values()))
        limit = entry["fidelity"]["tracker_alone_hand_deviation_max"]
        off = torch.tensor([max(s["hand_deviation_per_reader"]) > limit for s in entry["samples"]])
        ckpt, final, original, generated = load_flow_sets(run)
        data_first = original["observation"][:, 0].float()
        feats = features(final, original, generated, ckpt, data_first)
        assert len(off) == int(generated.sum()), (len(off), int(generated.sum()))
        tracked = torch.tensor([s["tracked_stop_rule"] for s in entry["samples"]], dtype=torch.float64)
        claimed = torch.tensor([s["claimed_stop_rule"] for s in entry["samples"]], dtype=torch.float64)
        feats["claimed_stop_rule"] = claimed
        res = {"num_generated": int(len(off)), "off_path": int(off.sum()), "bound_m": limit, "features": {}}
        for name, v in feats.items():
            res["features"][name] = {"auc_off_vs_on": auc(v[off], v[~off]),
                                     "median_off": float(v[off].median()) if off.any() else None,
                                     "median_on": float(v[~off].median()) if (~off).any() else None}
        res["tracked_mean_on"] = float(tracked[~off].mean()) if (~off).any() else None
        record["runs"][str(run)] = res
        print(run.name, f"off {int(off.sum())}/{len(off)}")
        for name, r in sorted(res["features"].items(), key=lambda kv: -abs((kv[1]["auc_off_vs_on"] or 0.5) - 0.5)):
            print(f"  {name:28s} auc {r['auc_off_vs_on']}  off {r['median_off']}  on {r['median_on']}")
        write_json(out_path, record)


if __name__ == "__main__":
    main()
