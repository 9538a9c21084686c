"""Does the ``cpu``-preset diffuser follow its condition at Meta-World's horizon on the toy task?

The Meta-World conditioning benches (``bench/diffuser_conditioning.py``) find that the
``cpu`` preset ignores its condition at H = 500. This one separates the horizon from the data:
the toy task (closed-form reward, ``torchrl_ftb.testing``) at the same horizon, blocks by
true return (K = 5), adjacent-block pairs, the ``cpu`` preset's training numbers, and every
``--steps / --evals`` steps 8 conditions per block B1–B4 sampled with the preset's sampler
(DDPM 25, guidance 1.2). Each sample's true return is recomputed from its generated actions.
``--distractor-dims D`` appends D observation dimensions that carry nothing about the reward
(a per-trajectory constant plus per-step noise, like Meta-World's goal and unused object
coordinates), to test the dimension of the data separately. D = 15 gives 20 diffused
dimensions, button-press-v3's count once its constant ones are left out (D = 36, all 39 of
Meta-World's observation dims, would exceed the preset's 32 full-resolution channels, a
bottleneck ``make_diffuser`` warns about, and so test something else).

    python bench/diffuser_conditioning_toy.py --horizon 500 --steps 1500
    python bench/diffuser_conditioning_toy.py --horizon 500 --steps 1500 --distractor-dims 15
    python bench/diffuser_conditioning_toy.py --distractor-dims 15 --override score_condition=true --tag score

``--override score_condition=true`` hands the encoder each condition's normalised score (here the
true return the blocks are cut from). 
Writes ``bench/results/diffuser_conditioning/toy-H<h>-D<d>-<steps>[-<tag>].json`` (command, config,
commit, machine, one row per evaluation).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch
from scipy.stats import spearmanr
from tensordict import TensorDict

from torchrl_ftb.data.labels import true_return
from torchrl_ftb.diffusion import DiffusionSampler, make_diffuser, parse_overrides, run_settings, train_diffuser
from torchrl_ftb.preference import NORMALIZED_SCORE_KEY, make_block_pair_buffer, make_blocks, with_normalized_scores
from torchrl_ftb.provenance import run_record, write_json
from torchrl_ftb.testing import make_toy_dataset, toy_reward

ROOT = Path(__file__).resolve().parents[1]


def with_distractors(data: TensorDict, dims: int, *, seed: int) -> TensorDict:
    """Append ``dims`` reward-irrelevant observation dims: per-trajectory constant + 0.05 noise."""
    if dims == 0:
        return data
    g = torch.Generator().manual_seed(seed + 1)
    n, h = data.batch_size
    extra = torch.randn(n, 1, dims, generator=g) + 0.05 * torch.randn(n, h, dims, generator=g)
    out = data.clone()
    out.set("observation", torch.cat([data["observation"], extra * data["mask"][..., None]], -1))
    return out


def sample_returns(diffuser, data, blocks, *, per_block: int, settings: dict, seed: int) -> dict:
    cond_idx = torch.cat([torch.nonzero(blocks == k).squeeze(-1)[:per_block] for k in range(int(blocks.max()))])
    keys = ["observation", "action", "mask"] + ([NORMALIZED_SCORE_KEY] if diffuser.score_condition else [])
    cond = data[cond_idx].select(*keys)
    sampler = DiffusionSampler(diffuser, sampler=settings["sampler"], steps=settings["sample_steps"],
                               guidance=settings["guidance"], seed=seed)
    smp = sampler(TensorDict({"condition": cond}, batch_size=[len(cond_idx)]))["sample"]
    ret = (toy_reward(smp["observation"], smp["action"]).squeeze(-1) * smp["mask"]).sum(-1)
    cb = blocks[cond_idx]
    k_max = int(blocks.max())
    return {
        "sample_return_by_condition_block": [float(ret[cb == k].mean()) for k in range(k_max)],
        "sample_length_by_condition_block": [float(smp["mask"][cb == k].sum(-1).float().mean()) for k in range(k_max)],
        "spearman_condition_block_vs_sample_return": float(spearmanr(cb.numpy(), ret.numpy()).statistic),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--horizon", type=int, default=500)
    p.add_argument("--num-trajectories", type=int, default=400)
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--evals", type=int, default=3)
    p.add_argument("--per-block", type=int, default=8)
    p.add_argument("--num-blocks", type=int, default=5)
    p.add_argument("--distractor-dims", type=int, default=0)
    p.add_argument("--preset", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE",
                   help="diffuser model fields, e.g. score_condition=true (the blocks' true returns are the scores)")
    p.add_argument("--tag", default="", help="suffix of the results file")
    args = p.parse_args(argv)
    try:
        overrides = parse_overrides(args.override)
    except ValueError as err:
        p.error(f"--override: {err}")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    data = with_distractors(make_toy_dataset(num_trajectories=args.num_trajectories, horizon=args.horizon,
                                             seed=args.seed), args.distractor_dims, seed=args.seed)
    returns = true_return(data)
    blocks = make_blocks(returns, args.num_blocks, seed=args.seed)
    settings = run_settings(args.preset)
    obs_dim = data["observation"].shape[-1]
    diffuser = make_diffuser(args.preset, obs_dim=obs_dim, action_dim=2, horizon=args.horizon, data=data,
                             **overrides)
    if diffuser.score_condition:  # blocks come from the true return here, so it is the score
        data = with_normalized_scores(data, returns)
    buffer = make_block_pair_buffer(data, blocks, batch_size=settings["batch_size"], seed=args.seed,
                                    scores=returns if diffuser.score_condition else None)
    tag = f"-{args.tag}" if args.tag else ""
    out = ROOT / "bench" / "results" / "diffuser_conditioning" / (
        f"toy-H{args.horizon}-D{args.distractor_dims}-{args.steps}{tag}.json")
    record = {**run_record(config={**vars(args), "settings": settings, "diffuser_config": diffuser.config}),
              "block_return_mean": [float(returns[blocks == k].mean()) for k in range(int(blocks.max()) + 1)],
              "block_length_mean": [float(data["mask"][blocks == k].sum(-1).float().mean())
                                    for k in range(int(blocks.max()) + 1)],
              "evaluations": []}
    done = 0
    with tempfile.TemporaryDirectory() as ckpt:
        for i in range(args.evals):
            target = args.steps * (i + 1) // args.evals
            t0 = time.time()
            res = train_diffuser(diffuser, buffer, steps=target, lr=settings["lr"], grad_clip=settings["grad_clip"],
                                 checkpoint_dir=ckpt, checkpoint_every=10**9, resume=True, progress=False,
                                 seed=args.seed)
            row = {"step": target, "train_seconds": round(time.time() - t0, 1), "loss": res["final_loss"],
                   **sample_returns(diffuser, data, blocks, per_block=args.per_block, settings=settings,
                                    seed=args.seed)}
            done = target
            record["evaluations"].append(row)
            write_json(out, record)
            print(row, flush=True)
    print(f"{done} steps -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
