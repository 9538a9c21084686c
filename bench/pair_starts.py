"""How far apart do a block pair's condition and target start? Uniform pairs vs start-matched ones.

FTB's diffuser learns from pairs (tau0 in B_k, tau1 in B_{k+1}). With the paper's uniform pairs the two
usually start in different situations (another object and goal position on Meta-World), while a flow step
asks for a better trajectory from its condition's own start. ``diffuser.pair_neighbours=m``
(:class:`torchrl_ftb.preference.BlockPairSampler`) pairs each condition with one of the m next-block
trajectories that start nearest to it. This bench draws pairs from a finished run's blocks both ways and
reports the mean start gap: the z-scored first observation (what the sampler compares) and, on Meta-World,
the hand's, the object's and the goal's positions in centimetres. Also the block sizes: where the next
block has at most m members the pairing is uniform anyway. No training; JSON with command, config,
commit and machine:

    python bench/pair_starts.py --run-dirs RUN... --neighbours 1,5,20 --out bench/results/pair_starts.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_generated import measure_runs, require_finished_runs  # noqa: E402
from torchrl_ftb.datasets import dataset_kwargs, make_dataset  # noqa: E402
from torchrl_ftb.envs import env_kind  # noqa: E402
from torchrl_ftb.preference import BlockPairSampler, standardized_starts  # noqa: E402

#: Meta-World observation slices (metres): the hand, the first object, the goal
METAWORLD_PARTS = {"hand_cm": slice(0, 3), "object_cm": slice(4, 7), "goal_cm": slice(36, 39)}


def start_views(starts: torch.Tensor, *, reference: torch.Tensor, metaworld: bool) -> dict[str, torch.Tensor]:
    """The first observations as this bench and ``diffuser_conditioning.py`` compare them: ``"z"`` (z-scored by
    ``reference``'s, :func:`~torchrl_ftb.preference.standardized_starts`) and, on Meta-World, the hand's, the
    object's and the goal's positions in cm (:data:`METAWORLD_PARTS`)."""
    views = {"z": standardized_starts(starts, reference=reference)}
    if metaworld:
        views.update({name: starts[:, part] * 100 for name, part in METAWORLD_PARTS.items()})
    return views


class _Sized:
    """The storage stand-in :meth:`BlockPairSampler.sample` needs (its length)."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n


def start_gaps(starts: torch.Tensor, block_ids: torch.Tensor, *, neighbours: int | None, pairs: int, seed: int,
               metaworld: bool) -> dict[str, float]:
    """Mean gap between the condition's and the target's start over ``pairs`` drawn pairs, per view of
    :func:`start_views`."""
    sampler = BlockPairSampler(block_ids, neighbours=neighbours, starts=starts if neighbours else None)
    sampler._rng = torch.Generator().manual_seed(seed)  # the replay buffer's generator, as a seeded buffer sets it
    index, _ = sampler.sample(_Sized(block_ids.numel()), pairs)
    return {name: float((view[index[:, 0]] - view[index[:, 1]]).norm(dim=-1).mean())
            for name, view in start_views(starts, reference=starts, metaworld=metaworld).items()}


def measure(run: Path, *, neighbours: list[int], pairs: int) -> dict:
    cfg = OmegaConf.load(run / "config.yaml")
    name = str(cfg.env.name)
    trajs, _ = make_dataset(name, **dataset_kwargs(name, cfg.dataset, progress=False,
                                                   max_episode_steps=int(cfg.env.max_episode_steps)))
    block_ids = torch.load(run / "checkpoints" / "blocks.pt", weights_only=True)["block_ids"]
    if block_ids.numel() != trajs.batch_size[0]:
        raise ValueError(f"{run}: blocks.pt holds {block_ids.numel()} trajectories, its dataset {trajs.batch_size[0]}")
    starts = trajs.get("observation")[:, 0].float()
    kw = {"pairs": pairs, "seed": int(cfg.seed), "metaworld": env_kind(name) == "metaworld"}
    gaps = {"uniform": start_gaps(starts, block_ids, neighbours=None, **kw)}
    for m in neighbours:
        gaps[f"neighbours_{m}"] = start_gaps(starts, block_ids, neighbours=m, **kw)
    return {"env": name, "seed": int(cfg.seed), "block_sizes": torch.bincount(block_ids).tolist(),
            "pair_neighbours_of_run": cfg.diffuser.get("pair_neighbours"), "mean_start_gap": gaps}


def describe(run: Path, entry: dict) -> str:
    rows = "; ".join(f"{pairing}: " + ", ".join(f"{k} {v:.2f}" for k, v in gap.items())
                     for pairing, gap in entry["mean_start_gap"].items())
    return f"{entry['env']} seed {entry['seed']} blocks {entry['block_sizes']}: {rows}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True,
                        help="finished runs (their blocks; checkpoints/blocks.pt)")
    parser.add_argument("--neighbours", default="1,5,20", help="comma-separated m of the start-matched pairings")
    parser.add_argument("--pairs", type=int, default=20000, help="pairs drawn per pairing")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "pair_starts.json")
    args = parser.parse_args()
    try:
        neighbours = [int(m) for m in args.neighbours.split(",")]
    except ValueError:
        parser.error(f"--neighbours {args.neighbours!r}: comma-separated integers >= 1")
    if any(m < 1 for m in neighbours) or args.pairs < 1:
        parser.error("--neighbours and --pairs must be >= 1")
    require_finished_runs(parser, args.run_dirs)
    measure_runs(args.run_dirs, args.out, {"neighbours": neighbours, "pairs": args.pairs},
                 lambda run: measure(run, neighbours=neighbours, pairs=args.pairs), describe)


if __name__ == "__main__":
    main()
