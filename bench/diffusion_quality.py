"""Benchmark: trajectory-diffuser sample quality vs sampler / step count on a Meta-World task.

Trains a diffuser (``cpu`` preset by default) on adjacent-block pairs of an IPL-style
Meta-World dataset, blocks from the *true* returns (quality of the diffuser alone, no score
model), then for each sampler/steps generates one trajectory per condition (conditions:
``--num-conditions`` trajectories from the lower blocks) and scores the generated (s, a)
with the ground-truth reward helper ``metaworld_true_reward``. Reports true-return gain over
the condition, success rate, generated length, out-of-range rate and ms per trajectory.
JSON to ``bench/results/diffusion_quality_<task>.json``. Not a test; the lead runs it.

Usage::

    nice -n 10 python bench/diffusion_quality.py --task button-press-v3 --train-steps 2000 \
        --samplers ddpm:50 ddpm:100 ddim:20 ddim:50 dpm++:20 --autocast-bf16
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_ftb.datasets.metaworld import make_metaworld_dataset
from torchrl_ftb.diffusion import DiffusionSampler, get_preset, make_diffuser, save_diffuser, train_diffuser
from torchrl_ftb.envs.metaworld import metaworld_true_reward
from torchrl_ftb.preference import make_block_pair_buffer, make_blocks
from torchrl_ftb.provenance import git_commit, machine_info, write_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="button-press-v3")
    parser.add_argument("--episodes-per-group", type=int, default=50)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--num-blocks", type=int, default=5)
    parser.add_argument("--train-steps", type=int, default=2000)
    parser.add_argument("--batch-size", type=int, default=None)
    parser.add_argument("--lr", type=float, default=None)
    parser.add_argument("--autocast-bf16", action="store_true")
    parser.add_argument("--samplers", nargs="+", default=["ddpm:50", "ddim:20", "dpm++:20"])
    parser.add_argument("--guidance", type=float, default=1.2)
    parser.add_argument("--num-conditions", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out-dir", default="runs/bench_diffusion_quality")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    preset = get_preset(args.preset)
    data, meta = make_metaworld_dataset(args.task, episodes_per_group=args.episodes_per_group, seed=args.seed)
    mask = data["mask"]
    true_return = (data["next", "reward"].squeeze(-1) * mask).sum(-1)
    blocks = make_blocks(true_return, args.num_blocks, seed=args.seed)
    n_blocks = int(blocks.max()) + 1
    batch_size = args.batch_size or preset["train"]["batch_size"]
    rb = make_block_pair_buffer(data, blocks, batch_size=batch_size, seed=args.seed)
    diffuser = make_diffuser(args.preset, obs_dim=data["observation"].shape[-1],
                             action_dim=data["action"].shape[-1], horizon=data.batch_size[1]).fit_normalizer(data)
    t0 = time.perf_counter()
    train = train_diffuser(diffuser, rb, steps=args.train_steps, lr=args.lr or preset["train"]["lr"],
                           grad_clip=preset["train"]["grad_clip"], autocast_bf16=args.autocast_bf16,
                           checkpoint_dir=args.out_dir, checkpoint_every=500, resume=True, seed=args.seed)
    train_wall = time.perf_counter() - t0
    save_diffuser(diffuser, Path(args.out_dir) / "diffuser_final.pt")
    low = torch.nonzero(blocks < n_blocks - 1).squeeze(-1)
    g = torch.Generator().manual_seed(args.seed)
    cond_idx = low[torch.randperm(len(low), generator=g)[: args.num_conditions]]
    cond = data[cond_idx]
    cond_r = true_return[cond_idx]
    next_block_mean = torch.stack([true_return[blocks == int(b) + 1].mean() for b in blocks[cond_idx]])
    results = []
    for spec in args.samplers:
        name, steps = spec.split(":")
        module = DiffusionSampler(diffuser, sampler=name, steps=int(steps), guidance=args.guidance, seed=args.seed,
                                  autocast_bf16=args.autocast_bf16, max_batch=16)
        t0 = time.perf_counter()
        sample = module(TensorDict({"condition": cond.select("observation", "action", "mask")},
                                   batch_size=[len(cond_idx)]))["sample"]
        wall = time.perf_counter() - t0
        reward, success = metaworld_true_reward(args.task, sample["observation"], sample["action"],
                                                mask=sample["mask"])
        gen_r = (reward.squeeze(-1) * sample["mask"]).sum(-1)
        z = diffuser.normalizer.normalize(diffuser.raw_data_from_td(sample))[sample["mask"]]
        res = {"sampler": name, "steps": int(steps), "ms_per_trajectory": 1000 * wall / len(cond_idx),
               "condition_return_mean": float(cond_r.mean()), "generated_return_mean": float(gen_r.mean()),
               "next_block_return_mean": float(next_block_mean.mean()),
               "return_gain_mean": float((gen_r - cond_r).mean()),
               "improved_fraction": float((gen_r > cond_r).float().mean()),
               "success_rate": float(success.squeeze(-1).any(-1).float().mean()),
               "condition_success_rate": float(data["next", "success"][cond_idx].squeeze(-1).any(-1).float().mean()),
               "length_mean": float(sample["mask"].sum(-1).float().mean()),
               "condition_length_mean": float(cond["mask"].sum(-1).float().mean()),
               "max_abs_z": float(z.abs().max()), "frac_steps_abs_z_gt_5": float((z.abs() > 5).any(-1).float().mean())}
        print(json.dumps(res), flush=True)
        results.append(res)
    payload = {"benchmark": "diffusion_quality", "command": " ".join(sys.argv), "config": vars(args),
               "preset": preset, "dataset_meta": meta, "num_blocks": n_blocks, "git_commit": git_commit(),
               "machine": machine_info(), "train": {k: v for k, v in train.items() if k != "losses"},
               "train_wall_s": train_wall, "loss_last100": sum(train["losses"][-100:]) / max(len(train["losses"][-100:]), 1),
               "results": results, "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    path = Path(__file__).resolve().parent / "results" / f"diffusion_quality_{args.task}.json"
    write_json(path, payload)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
