"""Benchmark: trajectory-diffuser training throughput and sampling cost on this machine.

Measures, for the ``cpu`` and ``paper`` presets (paper: a few steps only), fp32 vs bf16
autocast:
* training: seconds per optimisation step and trajectories/s (batch of pairs, horizon H);
* sampling: ms per generated trajectory and denoiser calls per trajectory (CFG batched).

Writes JSON to ``bench/results/diffusion_speed_<tag>.json`` with the command, config, git
commit, machine info and results. Not a test.

Usage::

    python bench/diffusion_speed.py --horizon 500 --obs-dim 39 --action-dim 4 --static-dims 24 \
        --presets cpu --train-steps 5 --sample-batch 8 --tag cpu_H500
    python bench/diffusion_speed.py --presets paper --paper-train-steps 1 --sample-batch 2 \
        --samplers dpm++:3 --no-bf16 --tag paper_H500
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_ftb.diffusion import DiffusionSampler, get_preset, make_diffuser, train_diffuser
from torchrl_ftb.provenance import git_commit, machine_info, write_json


def _random_trajectories(n: int, horizon: int, obs_dim: int, action_dim: int, seed: int,
                         static_dims: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    lengths = torch.randint(horizon // 2, horizon + 1, (n,), generator=g)
    mask = torch.arange(horizon) < lengths[:, None]
    m = mask[..., None].float()
    obs = torch.randn(n, horizon, obs_dim, generator=g)
    obs[..., :static_dims] = 0.5  # constant dims (Meta-World's zero-padded objects): not diffused
    return TensorDict({"observation": obs * m,
                       "action": torch.rand(n, horizon, action_dim, generator=g).mul(2).sub(1) * m,
                       "mask": mask}, batch_size=[n, horizon])


def bench_preset(preset: str, args, *, bf16: bool, train_steps: int) -> dict:
    torch.manual_seed(0)
    device = torch.device(args.device)
    data = _random_trajectories(64, args.horizon, args.obs_dim, args.action_dim, 0, args.static_dims)
    diffuser = make_diffuser(preset, obs_dim=args.obs_dim, action_dim=args.action_dim, horizon=args.horizon,
                             data=data, **json.loads(args.overrides)).to(device)
    batch_size = args.batch_size or get_preset(preset)["train"]["batch_size"]
    g = torch.Generator().manual_seed(1)

    def sample():
        i, j = torch.randint(0, 64, (batch_size,), generator=g), torch.randint(0, 64, (batch_size,), generator=g)
        return TensorDict({"condition": data[i], "target": data[j]}, batch_size=[batch_size])

    n_params = sum(p.numel() for p in diffuser.trainable_parameters())
    train_diffuser(diffuser, sample, steps=1, progress=False, device=device, autocast_bf16=bf16)  # warm-up
    t0 = time.perf_counter()
    out = train_diffuser(diffuser, sample, steps=train_steps, progress=False, device=device, autocast_bf16=bf16)
    wall = time.perf_counter() - t0
    result = {"preset": preset, "overrides": json.loads(args.overrides), "bf16": bf16, "parameters": n_params,
              "diffused_dims": diffuser.transition_dim, "batch_size": batch_size,
              "train_steps_timed": train_steps, "s_per_train_step": wall / max(train_steps, 1),
              "train_trajectories_per_s": batch_size * train_steps / wall, "final_loss": out["final_loss"]}
    calls = []
    hook = diffuser.ema.module["backbone"].register_forward_hook(lambda m, a, o: calls.append(a[0].shape[0]))
    cond = TensorDict({"condition": data[: args.sample_batch]}, batch_size=[args.sample_batch])
    samplers = [(spec.split(":")[0], int(spec.split(":")[1])) for spec in args.samplers]
    result["sampling"] = []
    for name, steps in samplers:
        calls.clear()
        module = DiffusionSampler(diffuser, sampler=name, steps=steps, seed=0, autocast_bf16=bf16)
        t0 = time.perf_counter()
        module(cond.clone())
        wall = time.perf_counter() - t0
        result["sampling"].append({"sampler": name, "steps": steps, "batch": args.sample_batch,
                                   "ms_per_trajectory": 1000 * wall / args.sample_batch,
                                   "denoiser_calls": len(calls),
                                   "denoiser_calls_per_trajectory": len(calls) / args.sample_batch,
                                   "denoiser_batch": calls[0] if calls else None})
    hook.remove()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--presets", nargs="+", default=["cpu", "paper"])
    parser.add_argument("--horizon", type=int, default=500)
    parser.add_argument("--obs-dim", type=int, default=39)
    parser.add_argument("--action-dim", type=int, default=4)
    parser.add_argument("--static-dims", type=int, default=24,
                        help="constant observation dims of the synthetic data (button-press-v3: 24 of 39)")
    parser.add_argument("--batch-size", type=int, default=None, help="default: the preset's")
    parser.add_argument("--train-steps", type=int, default=5)
    parser.add_argument("--paper-train-steps", type=int, default=2)
    parser.add_argument("--sample-batch", type=int, default=16)
    parser.add_argument("--samplers", nargs="+", default=["ddpm:25", "ddpm:50", "dpm++:20"],
                        help="sampler:steps to time (per-call cost x steps gives any other count)")
    parser.add_argument("--no-bf16", action="store_true")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--overrides", default="{}", help='model overrides as JSON, e.g. \'{"attention_factors": [1, 2, 4, 8]}\'')
    parser.add_argument("--tag", default=None)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    results = []
    for preset in args.presets:
        for bf16 in ([False] if args.no_bf16 else [False, True]):
            steps = args.paper_train_steps if preset == "paper" else args.train_steps
            res = bench_preset(preset, args, bf16=bf16, train_steps=steps)
            print(json.dumps(res), flush=True)
            results.append(res)
            # rewritten after every measurement: partial results survive a long paper-preset run
            tag = args.tag or f"H{args.horizon}_{args.device}"
            payload = {"benchmark": "diffusion_speed", "command": " ".join(sys.argv), "config": vars(args),
                       "git_commit": git_commit(), "machine": machine_info(), "results": results,
                       "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
            path = Path(__file__).resolve().parent / "results" / f"diffusion_speed_{tag}.json"
            write_json(path, payload)
            print(f"wrote {path}", flush=True)


if __name__ == "__main__":
    main()
