"""Benchmark: do the usual few-label remedies lift s_psi's ranking? (issue #3, exploratory)

With 30 full-trajectory labels the score model fits its pairs exactly and ranks the dataset at
Spearman 0.6-0.9 with the true return (``bench/score_model.py``); ``bench/score_groups.py`` shows the
errors sit inside the behaviour groups. This bench trains the recipe's score model (normalised
r_psi, 256x3, 500 full-batch Adam steps at lr 1e-3: the ``cpu`` preset) on the same labels with one
remedy at a time and reports Spearman(s_psi, true return) over the whole dataset per label seed:

* ``base``      -- the recipe's model, no remedy (must reproduce ``bench/score_model.py``);
* ``crop<L>``   -- temporal cropping (SURF, Park et al. 2022): every step both trajectories of a pair
  are cut to a random window of L valid steps (the whole trajectory when shorter);
* ``wd<x>``     -- Adam weight decay x;
* ``state``     -- a state-only reward: r_psi sees zero actions (Meta-World's reward is a function of
  the state), so it cannot tell behaviour groups apart by their action noise;
* ``pseudo<p>`` -- semi-supervised pseudo-labels (SURF): after the base training, 4,000 random
  dataset pairs are labelled by the model where it is more than p sure, and training continues
  for the same number of steps on the true labels + a batch of 64 pseudo-labelled pairs.

Not in the library: none of them helped (BENCHMARKS.md, score model). Not a test. Usage:
    python bench/score_model_variants.py --task button-press-v3 --variants base crop50 wd1e-2 state pseudo0.99
Writes bench/results/score_model_variants_<task>.json (command, config, commit, machine, results),
rewritten after every variant.
"""
from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parse_variant(name: str) -> dict:
    """``"crop50"`` -> ``{"crop": 50}``; ``"wd1e-2"``, ``"state"``, ``"pseudo0.99"``, ``"base"``."""
    patterns = {r"base": lambda m: {}, r"crop(\d+)": lambda m: {"crop": int(m[1])},
                r"wd([0-9.e-]+)": lambda m: {"weight_decay": float(m[1])}, r"state": lambda m: {"state_only": True},
                r"pseudo(0\.\d+)": lambda m: {"pseudo": float(m[1])}}
    for pattern, make in patterns.items():
        match = re.fullmatch(pattern, name)
        if match:
            return make(match)
    raise ValueError(f"unknown variant {name!r}: base | crop<L> | wd<x> | state | pseudo<p>")


def crop_window(trajs: TensorDictBase, length: int, generator: torch.Generator) -> TensorDictBase:
    """A random window of ``length`` valid steps per trajectory, as a narrower ``mask``.

    Hand-written because torchrl's ``RandomCropTensorDict`` refuses trajectories shorter than the
    window (Meta-World episodes end at success) and changes the time dimension.
    """
    mask = trajs.get("mask")
    valid = mask.sum(-1, keepdim=True)
    start = (torch.rand(valid.shape, generator=generator) * ((valid - length).clamp_min(0) + 1)).floor().long()
    t = torch.arange(mask.shape[-1])
    out = trajs.clone(False)
    out.set("mask", mask & (t >= start) & (t < start + length))
    return out


def _zero_actions(trajs: TensorDictBase) -> TensorDictBase:
    out = trajs.clone(False)
    out.set("action", torch.zeros_like(trajs.get("action")))
    return out


def train_variant(trajs: TensorDictBase, labels: TensorDictBase, variant: dict, *, seed: int, steps: int,
                  lr: float) -> torch.Tensor:
    """Train one score model with ``variant``'s remedy; return its scores of every trajectory."""
    from torchrl_ftb.preference import BradleyTerryLoss, ScoreModel, score_trajectories

    pool = trajs.select("observation", "action", "mask")
    if variant.get("state_only"):
        pool = _zero_actions(pool)
    model = ScoreModel(pool["observation"].shape[-1], pool["action"].shape[-1], seed=seed).fit_normalizer(pool)
    loss_fn = BradleyTerryLoss(model)
    labels = labels.select(*loss_fn.in_keys)
    if variant.get("state_only"):
        labels = TensorDict({"tau0": _zero_actions(labels["tau0"]), "tau1": _zero_actions(labels["tau1"]),
                             "label": labels["label"]}, labels.batch_size)
    optim = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=variant.get("weight_decay", 0.0))
    gen = torch.Generator().manual_seed(seed)

    def step(loss: torch.Tensor) -> None:
        optim.zero_grad()
        loss.backward()
        optim.step()

    for _ in range(steps):
        batch = labels
        if "crop" in variant:
            batch = TensorDict({"tau0": crop_window(labels["tau0"], variant["crop"], gen),
                                "tau1": crop_window(labels["tau1"], variant["crop"], gen),
                                "label": labels["label"]}, labels.batch_size)
        step(loss_fn(batch)["loss_preference"])
    if "pseudo" in variant:
        scores = score_trajectories(model, pool)
        n = pool.batch_size[0]
        i0, i1 = torch.randint(n, (4000,), generator=gen), torch.randint(n, (4000,), generator=gen)
        prob = torch.sigmoid(scores[i1] - scores[i0])
        keep = ((prob > variant["pseudo"]) | (prob < 1 - variant["pseudo"])) & (i0 != i1)
        pseudo = TensorDict({"tau0": pool[i0[keep]], "tau1": pool[i1[keep]], "label": (prob[keep] > 0.5).float()},
                            [int(keep.sum())])
        variant["pseudo_kept"] = variant.get("pseudo_kept", []) + [int(keep.sum())]
        for _ in range(steps):
            j = torch.randint(pseudo.batch_size[0], (64,), generator=gen)
            step(loss_fn(labels)["loss_preference"] + loss_fn(pseudo[j])["loss_preference"])
    return score_trajectories(model, pool)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="button-press-v3")
    parser.add_argument("--variants", nargs="+", default=["base", "crop50", "wd1e-2", "state", "pseudo0.99"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--out-dir", default=str(ROOT / "bench" / "results"))
    args = parser.parse_args()
    variants = {name: parse_variant(name) for name in args.variants}  # fail fast on a typo
    torch.set_num_threads(1)
    from torchrl_ftb.data.labels import METAWORLD_NUM_LABELS, ReturnTeacher, make_scripted_labels
    from torchrl_ftb.datasets import make_metaworld_dataset
    from torchrl_ftb.preference import correlations
    from torchrl_ftb.provenance import git_commit, machine_info, write_json

    trajs, meta = make_metaworld_dataset(args.task, episodes_per_group=100, noise=1.0, seed=0, progress=False)
    returns = ReturnTeacher().returns(trajs)
    out = Path(args.out_dir) / f"score_model_variants_{args.task}.json"
    record = {"benchmark": "score_model_variants", "command": " ".join([sys.executable, *sys.argv]),
              "config": dict(vars(args)), "commit": git_commit(), "machine": machine_info(),
              "dataset_path": meta.get("path"), "teacher": "return", "num_labels": METAWORLD_NUM_LABELS,
              "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "results": {}}
    for name, variant in variants.items():
        start, values = time.perf_counter(), []
        for seed in args.seeds:
            labels = make_scripted_labels(trajs, num_pairs=METAWORLD_NUM_LABELS, teacher=ReturnTeacher(), seed=seed)
            scores = train_variant(trajs, labels, variant, seed=seed, steps=args.steps, lr=args.lr)
            values.append(round(correlations(scores, returns)["spearman"], 4))
        mean = sum(values) / len(values)
        record["results"][name] = {"variant": variant, "spearman_return": values, "mean": round(mean, 4),
                                   "seconds": round(time.perf_counter() - start, 1)}
        print(f"{args.task} {name}: {values} mean {mean:.3f}", flush=True)
        record["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
        write_json(out, record)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
