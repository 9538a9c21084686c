"""Diagnose why a trained diffuser's samples pass or fail the flow's validity filter.

Loads the diffuser checkpoint of an FTB run directory, samples one trajectory for each of the
top-``n`` dataset trajectories (by true return), and reports each validity check of
:func:`torchrl_ftb.flow.trajectory_validity` with the values that decide it (max |z| on the
diffuser's normaliser scale and the dimension where it occurs, max |action|, detected length).
JSON to ``bench/results/flow_validity_<task>.json``.

Usage::

    python bench/flow_validity.py --run-dir runs/ftb_offline/<run> --num 8
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_ftb.datasets import dataset_kwargs, make_dataset
from torchrl_ftb.diffusion import DiffusionSampler, load_diffuser
from torchrl_ftb.flow import default_min_length, trajectory_validity
from torchrl_ftb.provenance import run_record, write_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run-dir", required=True)
    parser.add_argument("--num", type=int, default=8)
    parser.add_argument("--sampler", default="ddpm")
    parser.add_argument("--steps", type=int, default=25)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    run = Path(args.run_dir)
    cfg = OmegaConf.load(run / "config.yaml")
    name = cfg.env.name
    diffuser = load_diffuser(run / "checkpoints" / "diffuser" / "diffuser_last.pt")
    trajs, _ = make_dataset(name, **dataset_kwargs(name, cfg.dataset, max_episode_steps=int(cfg.env.max_episode_steps),
                                                   progress=False))
    ret = (trajs["next", "reward"].squeeze(-1) * trajs["mask"]).sum(-1)
    cond = trajs[ret.argsort(descending=True)[: args.num]].select("observation", "action", "mask")
    sampler = DiffusionSampler(diffuser, sampler=args.sampler, steps=args.steps,
                               generator=torch.Generator().manual_seed(args.seed))
    sample = sampler(TensorDict({"condition": cond}, [args.num]))["sample"]
    min_length = default_min_length(cond)
    checks = trajectory_validity(sample, normalizer=diffuser.normalizer, max_abs_z=float(cfg.flow.max_abs_z),
                                 min_length=min_length, action_tolerance=float(cfg.flow.action_tolerance))
    z = diffuser.normalizer.normalize(torch.cat([sample["observation"], sample["action"]], -1)).abs()
    z = z * sample["mask"][..., None]
    results = {
        "checks": {k: v.tolist() for k, v in checks.items()},
        "max_abs_z": z.amax((1, 2)).tolist(),
        "max_abs_z_dim": z.amax(1).argmax(-1).tolist(),
        "max_abs_action": (sample["action"].abs() * sample["mask"][..., None]).amax((1, 2)).tolist(),
        "length": sample["mask"].sum(-1).tolist(),
        "condition_length": cond["mask"].sum(-1).tolist(),
        "min_length": min_length,
    }
    for k, v in results.items():
        print(f"{k}: {v}")
    out = args.out or f"bench/results/flow_validity_{name}.json"
    write_json(out, {**run_record(config=vars(args)), "results": results})
    print(f"-> {out}")


if __name__ == "__main__":
    main()
