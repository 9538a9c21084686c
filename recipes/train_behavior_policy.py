"""Train a SAC behaviour policy on a gymnasium MuJoCo locomotion task (issue #7).

CPU-sized SAC in the style of torchrl's ``sota-implementations/sac`` (``SACLoss``,
``Collector`` (0.14 name of ``SyncDataCollector``), a memmap replay buffer, ``SoftUpdate``), used to make our own
D4RL-like datasets (``torchrl_ftb.datasets.locomotion``). Along the way it saves small actor
checkpoints with their deterministic evaluation return (``checkpoints/frames_XXXXXXX.pt``,
listed in ``progress.json``) and, at the end, the full replay buffer (``replay_buffer/``,
``ReplayBuffer.dumps``; every transition carries the simulator ``state`` and the collector's
trajectory id).

Ship the medium/expert policies and the medium-replay buffer of a finished run
(``torchrl_ftb/datasets/policies/``)::

    python recipes/train_behavior_policy.py --export-only --out-dir runs/behavior/hopper

Example (a 2-minute smoke run)::

    python recipes/train_behavior_policy.py --env Hopper-v5 --total-frames 3000 \
        --init-random-frames 1000 --eval-every 1000 --out-dir /tmp/sac_hopper

CPU runs used for the shipped policies (``nice -n 10``, one thread)::

    nice -n 10 python recipes/train_behavior_policy.py --env Hopper-v5 --max-wall-minutes 65 \
        --out-dir runs/behavior/hopper
"""
from __future__ import annotations

import argparse
import json
import platform
import signal
import sys
import time
from pathlib import Path

import torch
import tqdm
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer
from torchrl.modules import MLP, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate
from torchrl.record.loggers import get_logger

from torchrl_ftb.data.trajectories import atomic_write_text
from torchrl_ftb.datasets.locomotion import (
    POLICY_DIR,
    evaluate_policy,
    export_behavior_policies,
    make_behavior_actor,
    make_behavior_env,
    save_behavior_policy,
)
from torchrl_ftb.provenance import git_commit


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    # env
    p.add_argument("--env", default="Hopper-v5", help="Hopper-v5 | Walker2d-v5 | HalfCheetah-v5")
    p.add_argument("--seed", type=int, default=0)
    # collector
    p.add_argument("--total-frames", type=int, default=1_000_000)
    p.add_argument("--init-random-frames", type=int, default=5_000)
    p.add_argument("--frames-per-batch", type=int, default=1_000)
    p.add_argument("--max-wall-minutes", type=float, default=float("inf"),
                   help="stop (and save everything) after this much wall time")
    # replay buffer / optim
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--utd-ratio", type=float, default=1.0, help="gradient updates per env step")
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--target-update-polyak", type=float, default=0.995)
    p.add_argument("--alpha-init", type=float, default=1.0)
    # network
    p.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    # eval / logging
    p.add_argument("--eval-every", type=int, default=10_000, help="frames between checkpoint evaluations")
    p.add_argument("--eval-episodes", type=int, default=3)
    p.add_argument("--out-dir", default="runs/behavior/hopper")
    p.add_argument("--logger", default="csv", help="csv | wandb | tensorboard | '' (none)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-progress", action="store_true", help="disable the tqdm bar")
    # shipping
    p.add_argument("--export", action="store_true",
                   help="after training, ship medium/expert policies + medium-replay to --policy-dir")
    p.add_argument("--export-only", action="store_true", help="skip training; export an existing --out-dir run")
    p.add_argument("--policy-dir", default=str(POLICY_DIR))
    return p.parse_args(argv)


def make_qvalue(obs_dim: int, action_dim: int, hidden, device) -> ValueOperator:
    """Q(s, a) MLP, input ``[action, observation]`` (as in torchrl's SAC recipe)."""
    net = MLP(in_features=obs_dim + action_dim, out_features=1, num_cells=list(hidden),
              activation_class=nn.ReLU, device=device)
    return ValueOperator(net, in_keys=["action", "observation"])


_STOP = {"requested": False}


def _request_stop(signum, frame):
    # a flag, not an exception: interrupting a SACLoss call mid-vmap corrupts its state
    _STOP["requested"] = True


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.export_only:
        return export_behavior_policies(args.out_dir, out_dir=args.policy_dir, progress=not args.no_progress)
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    out = Path(args.out_dir)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)

    # float64 state: episodes of the buffer can be re-simulated exactly from their first state
    env = make_behavior_env(args.env, seed=args.seed, state_dtype=torch.float64)
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_spec = env.action_spec
    action_dim = action_spec.shape[-1]
    arch = {
        "env_name": args.env, "obs_dim": int(obs_dim), "action_dim": int(action_dim),
        "num_cells": list(args.hidden),
        "action_low": action_spec.space.low.tolist(), "action_high": action_spec.space.high.tolist(),
    }
    actor = make_behavior_actor(obs_dim=obs_dim, action_dim=action_dim, num_cells=args.hidden,
                                action_low=action_spec.space.low, action_high=action_spec.space.high,
                                device=device)
    qvalue = make_qvalue(obs_dim, action_dim, args.hidden, device)
    # initialise lazy modules / check wiring
    with torch.no_grad():
        td0 = env.reset()
        actor(td0.to(device))
        qvalue(actor(td0.to(device)))

    loss = SACLoss(actor_network=actor, qvalue_network=qvalue, num_qvalue_nets=2,
                   loss_function="l2", delay_actor=False, delay_qvalue=True,
                   alpha_init=args.alpha_init, action_spec=action_spec)
    loss.make_value_estimator(gamma=args.gamma)
    target = SoftUpdate(loss, eps=args.target_update_polyak)
    optim_actor = torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=args.lr)
    optim_critic = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=args.lr)
    optim_alpha = torch.optim.Adam([loss.log_alpha], lr=args.lr)

    rb = TensorDictReplayBuffer(
        storage=LazyMemmapStorage(args.total_frames, scratch_dir=out / "replay_scratch"),
        batch_size=args.batch_size,
    )
    collector = Collector(
        env, actor, frames_per_batch=args.frames_per_batch, total_frames=args.total_frames,
        init_random_frames=args.init_random_frames, device=device, auto_register_policy_transforms=False,
    )
    logger = get_logger(args.logger, logger_name=str(out / "logs"), experiment_name="sac") if args.logger else None
    config = {k: (v if v != float("inf") else None) for k, v in vars(args).items()}
    progress = {
        "command": " ".join([sys.executable, *sys.argv]), "config": config, "commit": git_commit(),
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "torch": torch.__version__, "threads": args.threads},
        "arch": arch, "checkpoints": [],
    }

    start = time.time()
    frames, updates, next_eval = 0, 0, args.eval_every
    pbar = tqdm.tqdm(total=args.total_frames, disable=args.no_progress, desc=f"SAC {args.env}")
    stop_reason = "total_frames"
    signal.signal(signal.SIGTERM, _request_stop)  # `kill PID` stops after the batch, and saves
    optimizers = (optim_critic, optim_actor, optim_alpha)
    for data in collector:
        data = data.reshape(-1).exclude("loc", "scale")
        rb.extend(data)
        frames += data.numel()
        pbar.update(data.numel())
        metrics = {}
        if frames >= args.init_random_frames:
            for _ in range(int(data.numel() * args.utd_ratio)):
                batch = rb.sample().to(device)
                losses = loss(batch)
                for opt in optimizers:
                    opt.zero_grad()
                # the actor loss uses detached Q parameters and the alpha loss a detached
                # log-prob, so one backward of the sum gives each optimizer its own gradient
                (losses["loss_qvalue"] + losses["loss_actor"] + losses["loss_alpha"]).backward()
                for opt in optimizers:
                    opt.step()
                target.step()
                updates += 1
            metrics = {k: float(v.detach()) for k, v in losses.items() if k.startswith("loss_") or k == "alpha"}
        collector.update_policy_weights_()
        if frames >= next_eval:
            next_eval += args.eval_every
            rets = evaluate_policy(actor, args.env, episodes=args.eval_episodes, seed=args.seed + 10_000)
            ret = sum(rets) / len(rets)
            ckpt = out / "checkpoints" / f"frames_{frames:07d}.pt"
            save_behavior_policy(actor, ckpt, config=arch, frames=frames, eval_return=ret)
            wall = time.time() - start
            progress["checkpoints"].append({"frames": frames, "updates": updates, "eval_return": ret,
                                            "path": str(ckpt.relative_to(out)), "wall_s": wall})
            progress["steps_per_s"] = frames / wall
            atomic_write_text(out / "progress.json", json.dumps(progress, indent=2))
            metrics["eval/return"] = ret
            pbar.set_postfix(eval_return=f"{ret:.0f}", fps=f"{frames / wall:.0f}")
        if logger is not None:
            for k, v in metrics.items():
                if v is not None and v == v:  # never log None / NaN
                    logger.log_scalar(k, v, step=frames)
        if (time.time() - start) / 60.0 > args.max_wall_minutes:
            stop_reason = "max_wall_minutes"
            break
        if _STOP["requested"]:
            stop_reason = "SIGTERM"
            break
    pbar.close()
    collector.shutdown()
    rb.dumps(out / "replay_buffer")
    progress.update(frames=frames, updates=updates, wall_s=time.time() - start, stop_reason=stop_reason,
                    replay_buffer="replay_buffer")
    atomic_write_text(out / "progress.json", json.dumps(progress, indent=2))
    if args.export:
        progress["export"] = export_behavior_policies(out, out_dir=args.policy_dir, progress=not args.no_progress)
    return progress


if __name__ == "__main__":
    main()
