"""Session 56: is a guided set's harm to BC a matter of how many generated paths join the top-k, or of which? BC
(session 53's bc_subsets.py: the run's recipe BC and its 50-episode evaluation) on the original top-k plus N generated
paths drawn at random (without replacement, draw seed D) from the final set's on-path or off-path ones (the readers
reading's split), for each N and D given. Button-press seed 5's ensemble-guided set poisons BC with either half (top-k
+ its 114 on-path paths: 0.40), seed 8's with neither (top-k + its 47 on-path paths: 1.00): top-k + 47 of seed 5's
on-path paths asks whether the count explains it. ``--drop-near R`` (button-press: obs[0:3] the hand, obs[4:7] the
button) leaves out the drawn paths' steps with the hand within R m of the button (their mask), asking whether the harm
sits in what they do at the button (session 56's near_button.py).

usage: python bench/results/session56_scripts/bc_dose.py RUN_DIR READERS.json OUT.json --pool on_path|off_path
       --n N [N ...] --draws D [D ...] [--drop-near R]
"""
import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session53_scripts"))
from bc_subsets import bc_eval, load_split  # noqa: E402
from near_button import near_button  # noqa: E402

from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("run", type=Path)
    p.add_argument("readers", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--pool", choices=("on_path", "off_path"), required=True)
    p.add_argument("--n", type=int, nargs="+", required=True)
    p.add_argument("--draws", type=int, nargs="+", default=[0])
    p.add_argument("--drop-near", type=float, default=None, help="mask the drawn paths' steps this near the button, m")
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg, final, original, generated, off = load_split(args.run, args.readers)
    keys = ("observation", "action", "mask")
    gen = final[generated].select(*keys)
    pool = gen[off] if args.pool == "off_path" else gen[~off]
    if args.drop_near is not None:
        pool.set("mask", pool["mask"].bool() & ~near_button(pool, args.drop_near))
    if max(args.n) > pool.batch_size[0]:
        raise ValueError(f"--n {max(args.n)}: the {args.pool} pool of {args.run} holds {pool.batch_size[0]} paths")
    record = {**run_record(config={**vars(args), "run": str(args.run), "readers": str(args.readers),
                                   "out": str(args.out), "bc_steps": int(cfg.bc.steps), "seed": int(cfg.seed),
                                   "eval_episodes": int(cfg.eval.num_episodes)}),
              "off_path": int(off.sum()), "generated": int(len(off)), "pool_size": int(pool.batch_size[0]), "cells": []}
    for n in args.n:
        for d in args.draws:
            pick = torch.randperm(pool.batch_size[0], generator=torch.Generator().manual_seed(d))[:n]
            res = {"pool": args.pool, "n": n, "draw": d, **bc_eval(cfg, torch.cat([original.select(*keys), pool[pick]]))}
            record["cells"].append(res)
            print(res, flush=True)
            write_json(args.out, record)


if __name__ == "__main__":
    main()
