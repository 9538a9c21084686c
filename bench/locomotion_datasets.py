"""Benchmark: our D4RL-style locomotion datasets (sizes, returns, behaviour-policy scores).

Builds ``<env>-{medium-replay, medium, medium-expert}`` from the SHIPPED policies
(``torchrl_ftb/datasets/policies``) in a fresh cache and reports, per dataset: size, return
distribution (min/median/max) and approximate D4RL-normalized scores (gymnasium v5 envs vs
D4RL's v2 reference returns), plus the behaviour policies' evaluation returns and how long the
rebuild took.

Usage: python bench/locomotion_datasets.py --envs hopper walker2d [--medium 100000 --medium-expert 200000]
Writes bench/results/locomotion_datasets.json (command, config, git commit, machine, results).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch


def main() -> None:
    from torchrl_ftb.datasets.locomotion import DEFAULT_NUM_TRANSITIONS, POLICY_DIR

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=["hopper", "walker2d"])
    parser.add_argument("--medium", type=int, default=DEFAULT_NUM_TRANSITIONS["medium"])
    parser.add_argument("--medium-expert", type=int, default=DEFAULT_NUM_TRANSITIONS["medium-expert"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "locomotion_datasets.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    from torchrl_ftb.data.trajectories import atomic_write_text
    from torchrl_ftb.datasets.locomotion import D4RL_NUM_TRANSITIONS, make_locomotion_dataset

    results = {}
    with tempfile.TemporaryDirectory() as cache:  # fresh cache: measure the rebuild
        for env in args.envs:
            record = json.loads((POLICY_DIR / f"{env}_policies.json").read_text())
            per_env = {
                "behaviour_policies": {
                    which: {k: p[k] for k in ("frames", "train_eval_return", "mean_return_deterministic",
                                              "mean_return_stochastic", "d4rl_normalized_score_approx", "bytes")}
                    for which, p in record["policies"].items()
                },
                "training": {k: record.get(k) for k in ("training_frames", "training_updates", "training_wall_s",
                                                        "training_steps_per_s", "stop_reason", "command")},
                "datasets": {},
            }
            for kind, n in (("medium-replay", None), ("medium", args.medium), ("medium-expert", args.medium_expert)):
                start = time.perf_counter()
                td, meta = make_locomotion_dataset(f"{env}-{kind}", num_transitions=n, seed=args.seed,
                                                   cache_dir=cache, progress=False)
                seconds = time.perf_counter() - start
                entry = {"rebuild_seconds": round(seconds, 1), "horizon": int(td.shape[1]),
                         "d4rl_size": D4RL_NUM_TRANSITIONS[kind], **meta["stats"]}
                if kind == "medium-expert":
                    group = meta["per_trajectory"]["group"]
                    ret = (td["next", "reward"].squeeze(-1) * td["mask"]).sum(-1)
                    entry["groups"] = {
                        name: {"episodes": int((group == g).sum()),
                               "transitions": int(td["mask"][group == g].sum()),
                               "return_median": float(ret[group == g].median())}
                        for g, name in enumerate(meta["groups"])
                    }
                if kind == "medium-replay":
                    entry["resimulation_check"] = meta["resimulation_check"]
                per_env["datasets"][kind] = entry
                print(env, kind, json.dumps({k: entry[k] for k in ("episodes", "transitions", "return_min",
                                                                    "return_median", "return_max",
                                                                    "rebuild_seconds")}), flush=True)
            results[env] = per_env
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip() or None
    except OSError:
        commit = None
    out = {
        "command": " ".join([sys.executable, *sys.argv]),
        "config": vars(args),
        "git_commit": commit,
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "torch": torch.__version__,
                    "load_avg_1m": os.getloadavg()[0]},
        "note": "D4RL-normalized scores are approximate: gymnasium v5 envs (mujoco 3) vs D4RL's v2 reference "
                "returns. Behaviour policies are our own CPU-trained SAC (see training), not D4RL's.",
        "results": results,
    }
    atomic_write_text(args.out, json.dumps(out, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
