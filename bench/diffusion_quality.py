"""Benchmark: trajectory-diffuser sample quality vs sampler / step count on a Meta-World task.

Trains a diffuser (``cpu`` preset by default) on adjacent-block pairs of an IPL-style
Meta-World dataset, blocks from the *true* returns (quality of the diffuser alone, no score
model) — or, with ``--checkpoint``, loads an already trained one (e.g. the
``checkpoints/diffuser/diffuser_last.pt`` of an FTB run) and skips training. Then for each
sampler/steps it generates one trajectory per condition (conditions: ``--num-conditions``
trajectories from the lower true-return blocks) and scores the generated (s, a) with the
ground-truth reward helper ``metaworld_true_reward``. Reports true return vs the condition's,
success rate, generated length, out-of-range rate, ms per trajectory and denoiser calls, and
a denoiser sanity check (eps-prediction MSE on real trajectories per timestep, see
:func:`denoiser_check`).

Dynamics error: there is no Meta-World one-step oracle here, so two *proxies* are reported,
both computable from generated (s, a) alone and both with a real-data reference value:

* ``framestack_err_mm``: Meta-World observations stack the previous frame, ``obs[t+1, 18:36]
  == obs[t, 0:18]`` (exact on the recorded data except rare object-position glitches): mean
  L2 violation over valid generated transitions, in mm (raw units x 1000).
* ``hand_dyn_err_mm``: one-step hand displacement ``obs[t+1, 0:3] - obs[t, 0:3]`` vs a linear
  (ridge) model of it on ``[obs[t], a[t], 1]`` fitted on 80 % of the real trajectories: mean L2
  residual in mm. Reference: the same residual on the held-out 20 % of real trajectories.

JSON to ``bench/results/diffusion_quality_<task>.json`` (``--results`` to override). Not a
test; the lead runs it.

Usage::

    nice -n 10 python bench/diffusion_quality.py --task button-press-v3 --train-steps 2000 \
        --samplers ddpm:50 ddpm:100 ddim:20 ddim:50 dpm++:20 --autocast-bf16
    nice -n 10 python bench/diffusion_quality.py --task button-press-v3 --episodes-per-group 100 \
        --checkpoint runs/ftb_offline/<run>/checkpoints/diffuser/diffuser_last.pt --threads 1 \
        --num-conditions 16 --samplers ddpm:1000 ddpm:25 ddim:20 ddim:50 dpm++:10 dpm++:20
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_ftb.datasets.metaworld import make_metaworld_dataset
from torchrl_ftb.diffusion import (DiffusionSampler, get_preset, load_diffuser, make_diffuser, save_diffuser,
                                   train_diffuser)
from torchrl_ftb.envs.metaworld import (fit_metaworld_hand_model, metaworld_frame_stack_error,
                                        metaworld_hand_model_error, metaworld_true_reward)
from torchrl_ftb.preference import make_block_pair_buffer, make_blocks
from torchrl_ftb.provenance import run_record, write_json


def dynamics_proxies(obs, act, mask, hand_w: torch.Tensor) -> dict:
    """Consistency proxies of trajectories ``[N, H]`` (mm; see the module docstring)."""
    td = TensorDict({"observation": obs.float(), "action": act.float(), "mask": mask.bool()}, obs.shape[:2])
    pairs = int((td["mask"][:, 1:] & td["mask"][:, :-1]).sum())
    return {"framestack_err_mm": 1000 * float(metaworld_frame_stack_error(td, pooled=True)),
            "hand_dyn_err_mm": 1000 * float(metaworld_hand_model_error(td, hand_w, pooled=True)),
            "num_transitions": pairs}


@torch.no_grad()
def denoiser_check(diffuser, trajs, *, timesteps=(10, 100, 500, 900, 999), seed: int = 0) -> dict:
    """Sanity check of the (EMA) denoiser on real trajectories: eps-prediction MSE per timestep.

    Predicting ``eps = 0`` scores 1.0; at ``t = 999`` (``abar ~ 2e-9``) ``x_t`` is the noise
    itself, so any working denoiser scores ~0 there. A value near 1 at every ``t`` means the
    network cannot carry its input through (e.g. too few channels for the transition size).
    """
    g = torch.Generator().manual_seed(seed)
    nets = diffuser.sampling_networks(True)
    was_training = nets.training
    nets.eval()
    raw, mask = diffuser.raw_data_from_td(trajs), trajs["mask"].bool()
    x0 = diffuser.model_input(raw, mask)
    emb = cmask = None
    if not diffuser.unconditional:
        emb, cmask = diffuser.encode_condition(diffuser.condition_input(raw, mask), mask, networks=nets)
    out = {}
    try:
        for t in timesteps:
            tt = torch.full((x0.shape[0],), int(t))
            noise = torch.randn(x0.shape, generator=g)
            x_t = diffuser.process.add_noise(x0, noise, tt)
            eps = diffuser.process.to_eps(x_t, nets["backbone"](x_t, tt, emb, cmask).float(), tt)  # eps-MSE either way
            err = (eps - noise).pow(2)
            out[str(t)] = {"mse_data": float((err[..., :-1] * mask[..., None]).sum() / (mask.sum() * diffuser.diffused_dim)),
                           "mse_validity": float(err[..., -1].mean())}
    finally:
        nets.train(was_training)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="button-press-v3")
    parser.add_argument("--episodes-per-group", type=int, default=50)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--checkpoint", default=None,
                        help="load this trained diffuser (load_diffuser) instead of training one")
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
    parser.add_argument("--results", default=None, help="results JSON (default bench/results/diffusion_quality_<task>.json)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    data, meta = make_metaworld_dataset(args.task, episodes_per_group=args.episodes_per_group, seed=args.seed)
    mask = data["mask"]
    true_return = (data["next", "reward"].squeeze(-1) * mask).sum(-1)
    blocks = make_blocks(true_return, args.num_blocks, seed=args.seed)
    n_blocks = int(blocks.max()) + 1

    train_info: dict | None = None
    checkpoint_info: dict | None = None
    if args.checkpoint:
        diffuser = load_diffuser(args.checkpoint)
        ckpt = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
        checkpoint_info = {"path": str(Path(args.checkpoint).resolve()), "config": ckpt.get("config"),
                           "step": ckpt.get("step")}
        del ckpt
        preset = get_preset(diffuser.config["preset"])
        for name, want in (("obs_dim", data["observation"].shape[-1]), ("action_dim", data["action"].shape[-1])):
            if getattr(diffuser, name) != want:
                raise SystemExit(f"--checkpoint: diffuser {name}={getattr(diffuser, name)} but the dataset has {want}")
    else:
        preset = get_preset(args.preset)
        batch_size = args.batch_size or preset["train"]["batch_size"]
        rb = make_block_pair_buffer(data, blocks, batch_size=batch_size, seed=args.seed)
        diffuser = make_diffuser(args.preset, obs_dim=data["observation"].shape[-1],
                                 action_dim=data["action"].shape[-1], horizon=data.batch_size[1], data=data)
        t0 = time.perf_counter()
        train = train_diffuser(diffuser, rb, steps=args.train_steps, lr=args.lr or preset["train"]["lr"],
                               grad_clip=preset["train"]["grad_clip"], autocast_bf16=args.autocast_bf16,
                               checkpoint_dir=args.out_dir, checkpoint_every=500, resume=True, seed=args.seed)
        train_info = {k: v for k, v in train.items() if k != "losses"}
        train_info["wall_s"] = time.perf_counter() - t0
        train_info["loss_last100"] = sum(train["losses"][-100:]) / max(len(train["losses"][-100:]), 1)
        save_diffuser(diffuser, Path(args.out_dir) / "diffuser_final.pt")

    # dynamics-proxy reference: linear hand model on 80 % of the real trajectories, residual on the rest
    g = torch.Generator().manual_seed(args.seed)
    perm = torch.randperm(data.batch_size[0], generator=g)
    n_fit = int(0.8 * len(perm))
    fit_idx, held_idx = perm[:n_fit], perm[n_fit:]
    hand_w = fit_metaworld_hand_model(data[fit_idx])
    reference = {"real_heldout": dynamics_proxies(data["observation"][held_idx], data["action"][held_idx],
                                                  mask[held_idx], hand_w)}

    low = torch.nonzero(blocks < n_blocks - 1).squeeze(-1)
    g = torch.Generator().manual_seed(args.seed)
    cond_idx = low[torch.randperm(len(low), generator=g)[: args.num_conditions]]
    cond = data[cond_idx]
    cond_r = true_return[cond_idx]
    next_block_mean = torch.stack([true_return[blocks == int(b) + 1].mean() for b in blocks[cond_idx]])
    reference["conditions"] = dynamics_proxies(cond["observation"], cond["action"], mask[cond_idx], hand_w)
    # the reward helper on the conditions' own (s, a), next obs shifted as for generated ones: its bias
    helper_r, _ = metaworld_true_reward(args.task, cond["observation"], cond["action"], mask=cond["mask"])
    cond_r_helper = (helper_r.squeeze(-1) * cond["mask"]).sum(-1)
    check = denoiser_check(diffuser, cond, seed=args.seed)
    print(json.dumps({"denoiser_check_eps_mse": check}), flush=True)
    print(json.dumps({"reference": reference, "condition_return_mean": float(cond_r.mean()),
                      "condition_return_helper_mean": float(cond_r_helper.mean())}), flush=True)
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
        chunks = -(-len(cond_idx) // 16)
        res = {"sampler": name, "steps": int(steps),
               # one batched (CFG) network call per sampler step and chunk of <= 16 conditions
               "denoiser_calls_per_trajectory": int(steps), "denoiser_calls_total": int(steps) * chunks,
               "ms_per_trajectory": 1000 * wall / len(cond_idx), "wall_s": wall,
               "condition_return_mean": float(cond_r.mean()), "generated_return_mean": float(gen_r.mean()),
               "next_block_return_mean": float(next_block_mean.mean()),
               "return_gain_mean": float((gen_r - cond_r).mean()),
               "improved_fraction": float((gen_r > cond_r).float().mean()),
               "success_rate": float(success.squeeze(-1).any(-1).float().mean()),
               "condition_success_rate": float(data["next", "success"][cond_idx].squeeze(-1).any(-1).float().mean()),
               "length_mean": float(sample["mask"].sum(-1).float().mean()),
               "condition_length_mean": float(cond["mask"].sum(-1).float().mean()),
               "max_abs_z": float(z.abs().max()), "frac_steps_abs_z_gt_5": float((z.abs() > 5).any(-1).float().mean()),
               **dynamics_proxies(sample["observation"], sample["action"], sample["mask"], hand_w)}
        print(json.dumps(res), flush=True)
        results.append(res)
    config = dict(vars(args))
    config["checkpoint"] = checkpoint_info["path"] if checkpoint_info else None
    payload = {"benchmark": "diffusion_quality", **run_record(config=config), "preset": preset,
               "dataset_meta": meta, "num_blocks": n_blocks,
               "condition_blocks": "lower blocks of make_blocks(true returns); a --checkpoint may have been "
                                   "trained on other (e.g. score-model) blocks",
               "checkpoint": checkpoint_info, "train": train_info,
               "dynamics_proxy": {"kind": "proxy (no Meta-World one-step oracle)",
                                  "framestack_err_mm": "mean ||obs[t+1,18:36]-obs[t,0:18]||_2 x 1000",
                                  "hand_dyn_err_mm": "mean ||dhand - linear([obs,a,1])||_2 x 1000, "
                                                     "ridge fit on 80% of real trajectories",
                                  "reference": reference},
               "condition_return_helper_mean": float(cond_r_helper.mean()),
               "denoiser_check_eps_mse": check,
               "results": results, "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
    path = Path(args.results) if args.results else (
        Path(__file__).resolve().parent / "results" / f"diffusion_quality_{args.task}.json")
    write_json(path, payload)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
