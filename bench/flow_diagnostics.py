"""Does the flow filter's score gain predict a true-return gain? One flow step, every sample.

Loads an FTB run directory of ``recipes/ftb_offline.py`` (its score model, blocks and diffuser
checkpoints), draws one sample for each of the top-``k`` dataset trajectories (the first flow
step of Alg. 4, with the run's sampler settings unless overridden), and records for *every*
sample — accepted or not — the score gain (on the flow's dataset-normalised scale), the true
return gain (ground-truth reward of the generated (s, a) sequence), the length change, the
validity checks and, for Meta-World, the frame-stack error (the 39-d observation repeats the
previous frame's 18 hand/object entries, ``obs[t + 1, 18:36] = obs[t, 0:18]`` in real data).
Reports how much the samples follow their conditions (Spearman of condition vs sample score,
return and length: ~0 for an unconditional draw), the Spearman correlation of score gain with
true gain, the share of accepted samples whose true return rose, and the same split by length
change. JSON to
``bench/results/flow_diagnostics/<task>-<tag>.json``.

Usage::

    python bench/flow_diagnostics.py --run-dir outputs/table1_obsnorm/button-press-v3/return/ftb/seed0 \\
        [--guidance 2.0] [--sampler dpm++ --steps 10] [--tag g2]
    python bench/flow_diagnostics.py --summarize bench/results/flow_diagnostics/*.json   # Markdown table
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Callable

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.data.labels import true_return  # noqa: E402
from torchrl_ftb.datasets import dataset_kwargs, make_dataset  # noqa: E402
from torchrl_ftb.diffusion import DiffusionSampler, get_preset, load_diffuser  # noqa: E402
from torchrl_ftb.envs import metaworld_frame_stack_error, true_reward_fn  # noqa: E402
from torchrl_ftb.flow import (  # noqa: E402
    FlowToBetter, clip_actions, default_min_length, improves, masked_true_return, masked_true_returns,
    normalized_scores, trajectory_validity,
)
from torchrl_ftb.preference import (  # noqa: E402
    correlations, load_score_model, score_trajectories, with_normalized_scores,
)
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman correlation (:func:`torchrl_ftb.preference.correlations`); NaN below 3 values."""
    return correlations(a, b)["spearman"] if a.numel() >= 3 else float("nan")


def sample_true_return(samples, reward_fn, *, horizon: int | None = None, streak: int | None = None) -> torch.Tensor:
    """True-reward-oracle return ``[N]`` of generated trajectories, actions clipped to the env's
    [-1, 1] first (as the flow does before accepting a sample). ``horizon`` / ``streak``: the
    stop-rule fill after the stop-rule cut (:func:`torchrl_ftb.flow.masked_true_returns`; ``streak``
    needs a ``reward_fn`` that also returns success); ``None``: the plain sum."""
    clipped = clip_actions(samples.clone(), 1.0)
    if streak is None:
        return masked_true_return(clipped, reward_fn, horizon=horizon)
    return masked_true_returns(clipped, reward_fn, horizons=(horizon,), streaks=(streak,))[:, 0]


def load_run(run: Path, *, with_returns: bool = False, horizon: int | None = None):
    """``(cfg, trajectories)`` of an FTB run directory: its resolved config and its dataset
    (``observation``, ``action``, ``mask``), rebuilt from the cache with the run's settings.
    ``with_returns=True`` also returns the dataset's true returns ``[N]`` (recorded rewards; with
    ``horizon``, the stop-rule fill of :func:`torchrl_ftb.data.labels.true_return`)."""
    cfg = OmegaConf.load(run / "config.yaml")
    name = str(cfg.env.name)
    trajs, _ = make_dataset(name, **dataset_kwargs(name, cfg.dataset, max_episode_steps=int(cfg.env.max_episode_steps),
                                                   progress=False))
    out = trajs.select("observation", "action", "mask")
    if not with_returns:
        return cfg, out
    if horizon is not None:
        return cfg, out, true_return(trajs, horizon=horizon).double()
    returns = (trajs.get(("next", "reward")).reshape(trajs.batch_size).double() * trajs.get("mask")).sum(-1)
    return cfg, out, returns


def sampling_settings(cfg, *, sampler: str | None = None, steps: int | None = None,
                      guidance: float | None = None) -> tuple[str, int, float]:
    """The run's sampler, steps and guidance (its config, else its diffuser preset), overridable."""
    preset = get_preset(str(cfg.diffuser.preset))["sample"]
    sampler = sampler or cfg.diffuser.sampler or preset["sampler"]
    steps = steps or cfg.diffuser.sample_steps or preset["steps"]
    guidance = guidance if guidance is not None else (cfg.diffuser.guidance or preset["guidance"])
    return str(sampler), int(steps), float(guidance)


def _summary(mask: torch.Tensor, d_true: torch.Tensor) -> dict:
    n = int(mask.sum())
    return {"n": n, "true_gain_positive": float((d_true[mask] > 0).double().mean()) if n else float("nan"),
            "true_gain_mean": float(d_true[mask].mean()) if n else float("nan")}


def summarize(paths: list[Path]) -> str:
    """Markdown table of saved diagnostics, recomputed from their per-sample records."""
    rows = ["| file | guidance | strength | valid | accepted | follows condition: score / return / length | score: condition → sample "
            "(dataset mean) | true return: condition → sample | Spearman(score gain, true gain) | accepted with true gain > 0 |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for path in paths:
        rec = json.loads(path.read_text())
        per, res = rec["per_sample"], rec["results"]
        t = {k: torch.tensor(v, dtype=torch.float64) for k, v in per.items() if not k.startswith("check_")
             and k != "improves"}
        valid = torch.tensor(per["check_valid"])
        acc = valid & torch.tensor(per["improves"])
        gain = t["true_new"] - t["true_old"]
        follow = [spearman(t[f"{k}_old"], t[f"{k}_new"]) for k in ("score", "true", "length")]
        ds_mean = res.get("mean_condition_vs_sample", {}).get("dataset_score_mean", float("nan"))
        rows.append(
            f"| {path.stem} | {res['guidance']} | {res.get('strength', 1.0)} | {valid.double().mean():.2f} | {int(acc.sum())} | "
            + " / ".join(f"{v:+.2f}" for v in follow)
            + f" | {t['score_old'].mean():.0f} → {t['score_new'].mean():.0f} ({ds_mean:.0f}) | "
            f"{t['true_old'].mean():.0f} → {t['true_new'].mean():.0f} | {res['spearman_score_gain_vs_true_gain']:.2f} | "
            + (f"{int((gain[acc] > 0).sum())} / {int(acc.sum())}" if bool(acc.any()) else "—") + " |")
    return "\n".join(rows)


def run_parser(doc: str) -> argparse.ArgumentParser:
    """The command line both run-directory benches share: ``--run-dir`` or ``--summarize FILES``."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--summarize", nargs="+", type=Path, default=None,
                        help="print a Markdown table of these saved JSONs and exit")
    parser.add_argument("--run-dir", type=Path, help="an FTB run directory of recipes/ftb_offline.py")
    parser.add_argument("--tag", default="", help="suffix of the results file")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    return parser


def parse_run_args(parser: argparse.ArgumentParser, summarize_fn: Callable[[list[Path]], str],
                   plot_fn: Callable[[list[Path], Path], Path] | None = None) -> argparse.Namespace | None:
    """Parse; with ``--summarize`` print ``summarize_fn(files)`` (and, given ``plot_fn`` and ``--plot PNG``, write
    ``plot_fn(files, PNG)``) and return None, else require ``--run-dir`` and set the torch threads."""
    args = parser.parse_args()
    if args.summarize:
        try:
            print(summarize_fn(args.summarize))
        except ValueError as err:  # a file that is not this bench's results: its name, not a traceback
            parser.error(f"--summarize: {err}")
        if plot_fn is not None and getattr(args, "plot", None) is not None:
            try:
                print(plot_fn(args.summarize, args.plot))
            except ValueError as err:
                parser.error(f"--plot: {err}")
        return None
    if args.run_dir is None:
        parser.error("--run-dir is required (or --summarize FILES)")
    torch.set_num_threads(args.threads)
    return args


def main() -> None:
    parser = run_parser(__doc__)
    parser.add_argument("--sampler", default=None, help="default: the run's (ddpm | ddim | dpm++)")
    parser.add_argument("--steps", type=int, default=None, help="sampler steps (default: the run's)")
    parser.add_argument("--guidance", type=float, default=None, help="default: the run's")
    parser.add_argument("--seed", type=int, default=None, help="default: the run's seed")
    parser.add_argument("--strength", type=float, default=None,
                        help="SDEdit strength in (0, 1] (DiffusionSampler(strength=...)); default 1: from noise, the paper")
    args = parse_run_args(parser, summarize)
    if args is None:
        return
    run = args.run_dir
    cfg, trajs = load_run(run)
    name, f = str(cfg.env.name), cfg.flow
    sampler_name, steps, guidance = sampling_settings(cfg, sampler=args.sampler, steps=args.steps,
                                                      guidance=args.guidance)
    model = load_score_model(run / "checkpoints" / "score_model.pt")
    diffuser = load_diffuser(run / "checkpoints" / "diffuser" / "diffuser_last.pt")
    seed = int(cfg.seed if args.seed is None else args.seed)
    strength = 1.0 if args.strength is None else float(args.strength)
    # the recipe's sampler: a seeded generator, so this is the run's first flow step
    sampler = DiffusionSampler(diffuser, sampler=sampler_name, steps=int(steps), guidance=float(guidance),
                               generator=torch.Generator().manual_seed(seed), strength=strength)
    scores = score_trajectories(model, trajs).double()
    s_min, s_max = float(scores.min()), float(scores.max())
    top = scores.argsort(descending=True)[: int(f.top_k)]
    cond = trajs[top]
    reward_fn = true_reward_fn(name)
    flow = FlowToBetter(sampler, model, top_k=int(f.top_k), flow_steps=1, batch_size=int(f.batch_size),
                        progress=False)
    t0 = time.time()
    # the conditions' normalised scores go along (read by a score_condition diffuser)
    samples = flow.generate(with_normalized_scores(cond, scores[top], s_min=s_min, s_max=s_max))
    sample_seconds = time.time() - t0
    new_scores = score_trajectories(model, samples).double()
    min_length = default_min_length(cond) if f.min_length is None else int(f.min_length)
    checks = trajectory_validity(samples, normalizer=diffuser.normalizer, max_abs_z=float(f.max_abs_z),
                                 min_length=min_length, action_tolerance=float(f.action_tolerance))
    valid = checks["valid"]
    better = improves(normalized_scores(new_scores, s_min, s_max), normalized_scores(scores[top], s_min, s_max),
                      float(f.threshold))
    accepted = valid & better
    true_old = masked_true_return(cond, reward_fn)
    true_new = sample_true_return(samples, reward_fn)
    d_score = normalized_scores(new_scores, s_min, s_max) - normalized_scores(scores[top], s_min, s_max)
    d_true = true_new - true_old
    d_len = (samples["mask"].sum(-1) - cond["mask"].sum(-1)).double()
    per = {
        "score_old": scores[top].tolist(), "score_new": new_scores.tolist(),
        "true_old": true_old.tolist(), "true_new": true_new.tolist(),
        "length_old": cond["mask"].sum(-1).tolist(), "length_new": samples["mask"].sum(-1).tolist(),
        **{f"check_{k}": v.tolist() for k, v in checks.items()}, "improves": better.tolist(),
    }
    results = {
        "num_samples": int(top.numel()), "sample_seconds": round(sample_seconds, 1),
        "sampler": sampler_name, "steps": int(steps), "guidance": float(guidance), "seed": seed,
        "strength": strength,
        "valid_rate": float(valid.double().mean()), "improve_rate": float(better.double().mean()),
        "accept_rate": float(accepted.double().mean()),
        "spearman_score_gain_vs_true_gain": spearman(d_score[valid], d_true[valid]),
        "spearman_length_gain_vs_true_gain": spearman(d_len[valid], d_true[valid]),
        "spearman_length_gain_vs_score_gain": spearman(d_len[valid], d_score[valid]),
        # does the sample follow its condition? (an unconditional draw gives ~0)
        "condition_following_spearman": {
            "score": spearman(scores[top], new_scores), "true_return": spearman(true_old, true_new),
            "length": spearman(cond["mask"].sum(-1).double(), samples["mask"].sum(-1).double()),
        },
        "mean_condition_vs_sample": {"score": [float(scores[top].mean()), float(new_scores.mean())],
                                     "true_return": [float(true_old.mean()), float(true_new.mean())],
                                     "dataset_score_mean": float(scores.mean())},
        "valid": _summary(valid, d_true), "accepted": _summary(accepted, d_true),
        "rejected_valid": _summary(valid & ~better, d_true),
        "accepted_same_or_shorter": _summary(accepted & (d_len <= 0), d_true),
        "accepted_longer": _summary(accepted & (d_len > 0), d_true),
        "true_return_max_condition": float(true_old.max()), "true_return_max_sample_valid":
            float(true_new[valid].max()) if bool(valid.any()) else float("nan"),
    }
    if trajs["observation"].shape[-1] == 39:
        fs_data = metaworld_frame_stack_error(trajs)
        fs = metaworld_frame_stack_error(samples)
        results["frame_stack_error"] = {"dataset_mean": float(fs_data.mean()), "dataset_max": float(fs_data.max()),
                                        "samples_mean": float(fs.mean()),
                                        "spearman_vs_true_gain": spearman(fs[valid], d_true[valid])}
        per["frame_stack_error"] = fs.tolist()
    for k, v in results.items():
        print(f"{k}: {v}")
    tag = f"-{args.tag}" if args.tag else ""
    out = ROOT / "bench" / "results" / "flow_diagnostics" / f"{name}-{run.name}{tag}.json"
    write_json(out, {**run_record(config={**vars(args), "run_dir": str(run)}), "results": results,
                     "per_sample": per})
    print(f"-> {out}")


if __name__ == "__main__":
    main()
