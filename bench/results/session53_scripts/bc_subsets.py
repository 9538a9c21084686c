"""Session 53: which of a guided flow's samples teach BC against success? BC (the recipe's actor, loss, steps, batch,
lr, weight decay and seed; its 50-episode evaluation) on subsets of one finished run's sets, split by the readers
reading (session 49's, bench/tracked_replay.py: a generated path is off path if any reading left its claimed hand
further than the tracker alone leaves a top-k path):

- ``topk``: the original top-k alone (the control);
- ``final``: the final set (the recipe's BC, reproduced);
- ``topk+on_path`` / ``topk+off_path``: the top-k plus the final set's on-path / off-path generated paths;
- ``on_path``: the on-path generated paths alone.

usage: python bench/results/session53_scripts/bc_subsets.py RUN_DIR READERS.json OUT.json [--subsets ...]
"""
import argparse
import functools
import json
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from flow_generated import load_flow_sets  # noqa: E402

from torchrl_ftb.data import trajectories_to_flat  # noqa: E402
from torchrl_ftb.envs import make_env  # noqa: E402
from torchrl_ftb.policy import evaluate_policy, make_bc_actor_for, make_transition_buffer, train_bc  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

SUBSETS = ("topk", "final", "topk+on_path", "topk+off_path", "on_path")


def subset(name: str, final, original, generated: torch.Tensor, off: torch.Tensor):
    keys = ("observation", "action", "mask")
    gen = final[generated].select(*keys)
    parts = {"topk": [original.select(*keys)], "final": [final.select(*keys)],
             "topk+on_path": [original.select(*keys), gen[~off]], "topk+off_path": [original.select(*keys), gen[off]],
             "on_path": [gen[~off]]}[name]
    return torch.cat([p for p in parts if p.batch_size[0]], 0)


def load_split(run: Path, readers: Path):
    """``(cfg, final, original, generated, off)``: a finished run's sets and each generated path's off-path flag from
    the readers reading ``readers`` (off path: any reading's hand deviation above the tracker-alone bound)."""
    cfg = OmegaConf.load(run / "config.yaml")
    entry = json.loads(readers.read_text())["runs"][str(run)]
    limit = entry["fidelity"]["tracker_alone_hand_deviation_max"]
    off = torch.tensor([max(s["hand_deviation_per_reader"]) > limit for s in entry["samples"]])
    _, final, original, generated = load_flow_sets(run)
    if len(off) != int(generated.sum()):
        raise ValueError(f"{readers}: {len(off)} readings for {int(generated.sum())} generated paths")
    return cfg, final, original, generated, off


def bc_eval(cfg, trajs, *, seed: int | None = None) -> dict:
    """BC as the run's recipe trains it (actor, steps, batch, lr, weight decay; ``seed`` default the run's) on
    ``trajs`` and its evaluation: ``{"trajectories", "transitions", "success_rate", "return_mean"}``."""
    b, name, seed = cfg.bc, str(cfg.env.name), int(cfg.seed if seed is None else seed)
    eval_env = functools.partial(make_env, name, seed=int(cfg.eval.seed), toy_horizon=int(cfg.dataset.horizon),
                                 max_episode_steps=int(cfg.env.max_episode_steps))
    flat = trajectories_to_flat(trajs)
    torch.manual_seed(seed)
    actor = make_bc_actor_for(flat, hidden=tuple(b.hidden), device="cpu")
    buffer = make_transition_buffer(flat, batch_size=int(b.batch_size), seed=seed)
    train_bc(actor, buffer, steps=int(b.steps), batch_size=int(b.batch_size), lr=float(b.lr),
             weight_decay=float(b.weight_decay), seed=seed, progress=False, device="cpu")
    ev = evaluate_policy(eval_env, actor, num_episodes=int(cfg.eval.num_episodes), seed=int(cfg.eval.seed),
                         max_steps=cfg.eval.max_steps, num_envs=cfg.eval.num_envs,
                         stop_on_success=bool(cfg.eval.stop_on_success), progress=False)
    return {"trajectories": int(trajs.batch_size[0]), "transitions": int(flat.numel()),
            "success_rate": float(ev["success_rate"]), "return_mean": float(ev["return_mean"])}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("run", type=Path)
    p.add_argument("readers", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--subsets", nargs="+", default=list(SUBSETS), choices=SUBSETS)
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg, final, original, generated, off = load_split(args.run, args.readers)
    record = {**run_record(config={"run": str(args.run), "readers": str(args.readers), "subsets": args.subsets,
                                   "bc_steps": int(cfg.bc.steps), "seed": int(cfg.seed),
                                   "eval_episodes": int(cfg.eval.num_episodes)}),
              "off_path": int(off.sum()), "generated": int(len(off)), "subsets": {}}
    for sub in args.subsets:
        record["subsets"][sub] = bc_eval(cfg, subset(sub, final, original, generated, off))
        print(sub, record["subsets"][sub], flush=True)
        write_json(args.out, record)


if __name__ == "__main__":
    main()
