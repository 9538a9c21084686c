"""What did the flow put into the final set? One row per generated trajectory of an FTB run.

Reads a finished run of ``recipes/ftb_offline.py`` (its ``checkpoints/flow.pt``) and reports,
for every generated trajectory the flow accepted, its length, the flow step that produced it,
its true return as the flow recorded it, and for Meta-World its frame-stack error in metres
(:func:`torchrl_ftb.envs.metaworld_frame_stack_error`; 0 for real data) -- whether a high
"true return" belongs to a physically consistent trajectory. No sampling, no training. JSON to
``bench/results/flow_generated.json`` (command, config, commit, machine).

Usage::

    python bench/flow_generated.py --run-dirs outputs/table1_v2/sweep-into-v3/return/ftb/seed1
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.envs import metaworld_frame_stack_error  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "flow_generated.json")
    args = parser.parse_args()
    record = {**run_record(config={"run_dirs": [str(r) for r in args.run_dirs]}), "runs": {}}
    for run in args.run_dirs:
        cfg = OmegaConf.load(run / "config.yaml")
        ckpt = torch.load(run / "checkpoints" / "flow.pt", weights_only=True)
        final = TensorDict(ckpt["trajectories"]["data"], batch_size=ckpt["trajectories"]["batch_size"])
        generated = ckpt["source_step"] > 0
        rows = []
        if bool(generated.any()):
            gen = final[generated]
            obs_dim = gen.get("observation").shape[-1]
            stack = metaworld_frame_stack_error(gen).tolist() if obs_dim == 39 else [None] * gen.batch_size[0]
            true = ckpt.get("true_returns")
            for i, j in enumerate(generated.nonzero().squeeze(-1).tolist()):
                rows.append({"length": int(gen.get("mask")[i].sum()), "flow_step": int(ckpt["source_step"][j]),
                             "score": float(ckpt["scores"][j]),
                             "true_return": None if true is None else float(true[j]),
                             "frame_stack_error_m": stack[i]})
        record["runs"][str(run)] = {"env": str(cfg.env.name), "seed": int(cfg.seed),
                                    "teacher": str(cfg.labels.teacher), "generated_in_final_set": rows}
        print(f"{cfg.env.name} seed {cfg.seed}: " + "; ".join(
            f"len {r['length']} return {r['true_return']:.0f} frame-stack {r['frame_stack_error_m']}" for r in rows))
        write_json(args.out, record)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
