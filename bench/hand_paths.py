"""Where do a run's generated hand paths part from what their actions do? Per-step hand moves and open-loop drift.

For finished FTB run directories on generated Meta-World data: the hand's per-step displacement in the
dataset (median, 99.9th percentile, maximum) against the final set's generated trajectories (the first step,
where ``diffuser.inpaint_start`` joins a held start to the sample, and the share of samples with a step above the
data's maximum), and, for the first ``--replays`` generated trajectories, how far the hand of their open-loop
replay (:func:`torchrl_ftb.datasets.metaworld.replay_metaworld_actions`, from the nearest dataset start) is from
the generated hand path at given steps.

Usage::

    python bench/hand_paths.py --run-dirs RUN [RUN ...] --replays 40 --out bench/results/hand_paths.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_generated import measure_runs, require_finished_runs  # noqa: E402
from open_loop import load_flow  # noqa: E402

from torchrl_ftb.analysis import episode_jobs, nearest_start  # noqa: E402
from torchrl_ftb.datasets.metaworld import replay_metaworld_actions  # noqa: E402
from torchrl_ftb.envs import metaworld_hand_steps  # noqa: E402

DRIFT_STEPS = (10, 25, 50, 100, 200)


def hand_paths(run: Path, *, replays: int) -> dict:
    cfg, data, meta, final, _, generated, _ = load_flow(run)
    step, pair = metaworld_hand_steps(data)
    real = step[pair].float()
    q50, q999 = torch.quantile(real, torch.tensor([0.5, 0.999])).tolist()
    out = {"env": str(cfg.env.name), "seed": int(cfg.seed), "inpaint_start": bool(cfg.diffuser.get("inpaint_start", False)),
           "data_step_median": q50, "data_step_p999": q999, "data_step_max": float(real.max())}
    gen = final[generated]
    out["num_generated"] = int(gen.batch_size[0])
    if not out["num_generated"]:
        return out
    gstep, gpair = metaworld_hand_steps(gen)
    out["generated_first_step_median"] = float(gstep[:, 0].median())
    out["generated_later_step_median"] = float(gstep[:, 1:][gpair[:, 1:]].median())
    out["generated_above_data_max"] = float(((gstep > real.max()) & gpair).any(-1).double().mean())
    sub = gen[:replays]
    rows, _ = nearest_start(sub["observation"][:, 0].float(), data["observation"][:, 0])
    lengths = sub["mask"].sum(-1).tolist()
    eps = replay_metaworld_actions(str(cfg.env.name), episode_jobs(meta, rows),
                                   [sub["action"][i, :n].numpy() for i, n in enumerate(lengths)],
                                   seed=int(meta["seed"]), max_steps=int(meta["max_steps"]))
    drift = {}
    for t in DRIFT_STEPS:
        d = [float((torch.as_tensor(ep["observation"][t, 0:3]) - sub["observation"][i, t, 0:3].double()).norm())
             for i, ep in enumerate(eps) if len(ep["observation"]) > t]
        drift[str(t)] = {"n": len(d), "median": float(torch.tensor(d).median()) if d else None}
    out["replays"] = len(eps)
    out["replay_hand_off_path"] = drift
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--replays", type=int, default=40, help="generated trajectories to replay open loop")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "hand_paths.json")
    args = parser.parse_args()
    require_finished_runs(parser, args.run_dirs)
    measure_runs(args.run_dirs, args.out, {"replays": args.replays},
                 lambda run: hand_paths(run, replays=args.replays),
                 lambda run, e: f"{run} {({k: v for k, v in e.items() if k != 'replay_hand_off_path'})} "
                                f"{e.get('replay_hand_off_path')}")


if __name__ == "__main__":
    main()
