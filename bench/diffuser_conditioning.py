"""Does the trajectory diffuser follow its condition, and after how many training steps?

FTB's diffuser is trained on pairs (tau_0 in block k, tau_1 in block k + 1): a sample
conditioned on a block-k trajectory should look like a block-(k + 1) one. This bench copies
the diffuser checkpoint of an FTB run (``recipes/ftb_offline.py``), continues its training on
the run's own block pairs (same buffer, optimiser state and RNG: ``train_diffuser(resume=True)``)
-- or, with ``--preset``, trains a fresh diffuser of that preset on the same pairs -- and,
every ``--eval-every`` steps, samples one trajectory for each of ``--per-block`` conditions
from every block but the last, scoring the samples with the run's score model and with the
true-reward oracle. Reported per evaluation: the Spearman correlation of the sample's score
(and true return) with the condition's block (an unconditional model gives ~0), the mean
sample score / true return per condition block next to the dataset's mean of the block the
pairs taught it to produce (k + 1), and the mean generated length. ``--pairs copy`` trains on
pairs whose target *is* the condition (a copy task: can the condition path carry a whole
trajectory at all?); then the sample should match its condition (``spearman_sample_score_vs_
condition_score`` near 1), whatever the blocks. ``--top-block`` also samples from conditions of the
top block (the flow's top-k come from there; Eq. 5's pairs never use it as a condition, a run's
``diffuser.top_block_pairs`` does, and the bench trains on the run's own pairing), with the max
true return of conditions and samples and the share of samples above their own condition.
``--horizon 500 --streak 25`` scores the true returns (data and samples) with the stop-rule fill
after the stop-rule cut, the definition of the flow's ``true_return_filled_stop_rule_*`` statistics. ``--preset P
--stride S`` trains the fresh diffuser on every S-th step (:func:`~torchrl_ftb.data.coarsen_trajectories`) and reads
its samples at the data's horizon (:func:`~torchrl_ftb.data.refine_trajectories`), beside each block's conditions'
own round trip (``bench/coarsen_round_trip.py`` measures what a round trip keeps). ``--pair-weights 0,0,1,1``
trains the fresh diffuser only on the pairs into the top blocks (``BlockPairSampler(block_weights=...)``);
``--hold`` trains and conditions it on trajectories held at their last step to the full horizon
(:func:`~torchrl_ftb.data.hold_last_step`: nothing padded, so no length to generate; every length then reads
the horizon) and cuts its samples by the ``--streak`` stop rule; ``--pair-neighbours M`` pairs each condition with
one of the M next-block trajectories that start nearest to it. All three are locked to the work dir's checkpoint.
Every evaluation also gives the *trajectory gap*: each sample's mean squared distance to its own condition against
the others', in the diffuser's normalised space (0: a copy). JSON to
``bench/results/diffuser_conditioning/<task>-<run>-<tag>.json`` after every evaluation
(partial results survive a kill). ``--device cuda --autocast-bf16 --max-minutes M`` is the
GPU check (paper preset) that decides whether our CPU-budget findings are about the budget.

Usage::

    python bench/diffuser_conditioning.py --run-dir outputs/exp/bp-norm-gc --steps 4500 --eval-every 1500
    python bench/diffuser_conditioning.py --run-dir RUN --preset paper --steps 20000 --eval-every 2000 \
        --device cuda --autocast-bf16 --max-minutes 7 --tag paper-gpu
    python bench/diffuser_conditioning.py --summarize bench/results/diffuser_conditioning/*.json
    python bench/diffuser_conditioning.py --summarize A.json --plot conditioning.png   # and a plot of A
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_diagnostics import (  # noqa: E402
    load_run, parse_run_args, run_parser, sample_true_return, sampling_settings, spearman,
)
from pair_starts import start_views  # noqa: E402

from torchrl_ftb.data import coarsen_trajectories, hold_last_step, refine_trajectories  # noqa: E402
from torchrl_ftb.diffusion import (  # noqa: E402
    get_preset, load_diffuser, make_diffuser, parse_overrides, train_diffuser,
)
from torchrl_ftb.envs import observation_layout, true_reward_fn  # noqa: E402
from torchrl_ftb.preference import (  # noqa: E402
    load_score_model, make_block_pair_buffer, score_objective, score_trajectories, with_normalized_scores,
)
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def evaluate(diffuser, model, trajs, scores, ids, *, per_block: int, sampler: str, steps: int, guidance: float,
             seed: int, returns: torch.Tensor | None = None, reward_fn=None, autocast_bf16: bool = False,
             top_block: bool = False, horizon: int | None = None, streak: int | None = None,
             stride: int = 1, strength: float = 1.0, inpaint_start: bool = False, score_guidance: float = 0.0) -> dict:
    """Condition-following statistics of one model state (see module docstring).

    ``top_block=True`` also conditions on the top block, which Eq. 5's pairs never use as a condition
    (no block above it; ``diffuser.top_block_pairs`` pairs it with itself): the flow's top-k come from there.
    Its entry has no target block (None); the correlations are over the other blocks' conditions, as without it. ``strength < 1`` samples SDEdit
    edits of each condition and ``inpaint_start`` holds each sample's first observation at its condition's,
    as the recipe's ``diffuser.strength`` / ``diffuser.inpaint_start`` do in the flow; ``score_guidance`` pushes
    the samples up ``model``'s normalised score as the recipe's ``diffuser.score_guidance`` does.
    """
    gen = torch.Generator().manual_seed(seed)
    num_blocks = int(ids.max()) + 1
    picks, blocks = [], []
    for k in range(num_blocks if top_block else num_blocks - 1):
        members = (ids == k).nonzero().squeeze(-1)
        order = torch.randperm(members.numel(), generator=torch.Generator().manual_seed(seed + k))
        chosen = members[order[:per_block]]
        picks.append(chosen)
        blocks += [k] * chosen.numel()
    idx = torch.cat(picks)
    blocks = torch.tensor(blocks)
    conditions = trajs[idx]
    full_horizon = trajs.batch_size[1]
    cond = coarsen_trajectories(conditions, stride) if stride > 1 else conditions  # what the model is given
    edit = strength < 1.0 or inpaint_start  # the flow's options: the condition is also the init
    sample = diffuser.generate(cond, sampler=sampler, steps=steps, guidance=guidance, generator=gen,
                               autocast_bf16=autocast_bf16, init=cond if edit else None, strength=strength,
                               inpaint_start=inpaint_start, guide_scale=score_guidance,
                               guide=score_objective(model, float(scores.min()), float(scores.max()))
                               if score_guidance else None).to("cpu")
    gap = trajectory_gaps_to_conditions(diffuser, sample, cond.to("cpu"))
    round_trip = None
    if stride > 1:
        sample = refine_trajectories(sample.select("observation", "action", "mask"), stride, horizon=full_horizon)
        round_trip = refine_trajectories(cond.select("observation", "action", "mask").to("cpu"), stride,
                                         horizon=full_horizon)
        s_round = score_trajectories(model, round_trip).double()
        true_round = (sample_true_return(round_trip, reward_fn, horizon=horizon, streak=streak).double()
                      if reward_fn is not None and returns is not None else None)
    s_new = score_trajectories(model, sample).double()
    true_new = None
    if reward_fn is not None and returns is not None:
        true_new = sample_true_return(sample, reward_fn, horizon=horizon, streak=streak).double()
    length = sample["mask"].sum(-1).double()
    per = {}
    for k in range(int(blocks.max()) + 1):
        m, target = blocks == k, ids == k + 1  # the top block has no target (all False)
        has_target = bool(target.any())
        per[str(k + 1)] = {"condition_score": float(scores[idx[m]].mean()), "sample_score": float(s_new[m].mean()),
                           "target_block_score": float(scores[target].mean()) if has_target else None,
                           "condition_score_max": float(scores[idx[m]].max()), "sample_score_max": float(s_new[m].max()),
                           "sample_length": float(length[m].mean()),
                           "target_block_length": float(trajs["mask"][target].sum(-1).double().mean())
                           if has_target else None}
        if true_new is not None:
            per[str(k + 1)].update(condition_true_return=float(returns[idx[m]].mean()),
                                   sample_true_return=float(true_new[m].mean()),
                                   target_block_true_return=float(returns[target].mean()) if has_target else None,
                                   condition_true_return_max=float(returns[idx[m]].max()),
                                   sample_true_return_max=float(true_new[m].max()),
                                   samples_above_condition=float((true_new[m] > returns[idx[m]]).double().mean()))
        if round_trip is not None:
            per[str(k + 1)]["condition_round_trip_score"] = float(s_round[m].mean())
            if true_new is not None:
                per[str(k + 1)].update(condition_round_trip_true_return=float(true_round[m].mean()),
                                       condition_round_trip_true_return_max=float(true_round[m].max()),
                                       samples_above_round_trip=float((true_new[m] > true_round[m]).double().mean()))
    per_start = start_gaps_to_conditions(sample["observation"][:, 0].float(),
                                         conditions["observation"][:, 0].float(), trajs["observation"][:, 0].float())
    inner = blocks < num_blocks - 1  # the correlations: blocks that are conditions in training
    extra = {} if true_new is None else {
        "spearman_sample_true_return_vs_condition_block": spearman(blocks[inner].double(), true_new[inner])}
    return {**extra, "spearman_sample_score_vs_condition_block": spearman(blocks[inner].double(), s_new[inner]),
            "spearman_sample_score_vs_condition_score": spearman(scores[idx[inner]], s_new[inner]),
            "per_condition_block": per, "num_conditions": int(idx.numel()), "start_gap": per_start,
            "trajectory_gap": gap}


def trajectory_gaps_to_conditions(diffuser, sample, conditions) -> dict[str, float]:
    """How close is each sample to its own condition, in the diffuser's own (normalised) space and at its
    resolution? The mean squared difference per step and diffused dimension over the steps both have, to its own
    condition (``own``) and, averaged, to every other one (``other``). A copy is ``own`` ~ 0; a sample that
    ignores its condition has ``own`` ~ ``other``; two independent data trajectories are ~ 2 apart."""
    z_s = diffuser.condition_input(diffuser.raw_data_from_td(sample), sample["mask"]).double()
    z_c = diffuser.condition_input(diffuser.raw_data_from_td(conditions), conditions["mask"]).double()
    both = (sample["mask"].bool()[:, None] & conditions["mask"].bool()[None]).double()  # [n samples, n conds, H]
    sq = ((z_s[:, None] - z_c[None]) ** 2).mean(-1)  # [n, n, H]
    dist = (sq * both).sum(-1) / both.sum(-1).clamp(min=1)
    n, own = dist.shape[0], dist.diagonal()
    return {"own": float(own.mean()), "other": float(((dist.sum(1) - own) / max(n - 1, 1)).mean())}


def start_gaps_to_conditions(sample_starts: torch.Tensor, condition_starts: torch.Tensor,
                             data_starts: torch.Tensor) -> dict[str, float]:
    """Does a sample start where its condition starts? The mean distance of each sample's first observation to
    its own condition's (``own``) and, averaged, to every other condition's (``other``): z-scored by the
    dataset's starts, and on Meta-World (39-d) the object's and the goal's positions in cm. ``own`` well below
    ``other`` means the condition path carries the start (what start-matched pairs teach)."""
    n, metaworld = sample_starts.shape[0], sample_starts.shape[-1] == 39
    samples = start_views(sample_starts, reference=data_starts, metaworld=metaworld)
    conditions = start_views(condition_starts, reference=data_starts, metaworld=metaworld)
    out = {}
    for name, a in samples.items():
        dist = torch.cdist(a.double(), conditions[name].double())  # [n samples, n conditions]
        own = dist.diagonal()
        out[f"{name}_own"] = float(own.mean())
        out[f"{name}_other"] = float(((dist.sum(1) - own) / max(n - 1, 1)).mean())
    return out


def _weights(text: str) -> list[float]:
    """``--pair-weights`` value: comma-separated numbers (``BlockPairSampler`` checks them against the run's
    blocks: one per transition, non-negative, not all zero)."""
    try:
        return [float(w) for w in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated numbers, e.g. 0,0,1,1") from None


def _num(value: float | None) -> str:
    return "—" if value is None else f"{value:.0f}"  # the top block has no target block


def summarize(paths: list[Path]) -> str:
    """Markdown table of saved results: one row per (file, evaluation). ``--stride`` files also give each block's
    conditions' own round trip (coarsened and refined), the level a coarse model's samples are read against;
    ``--top-block`` files the share of top-block samples above their own condition and the samples' max."""
    rows = []
    for path in paths:
        try:
            rows += _summary_rows(path, json.loads(Path(path).read_text()), header=not rows)
        except (KeyError, TypeError, AttributeError, json.JSONDecodeError) as err:
            raise ValueError(f"{path}: not a diffuser_conditioning results file ({type(err).__name__}: {err})") from None
    return "\n".join(rows)


def _summary_cell(v: dict) -> str:
    """One condition block's cell of :func:`summarize`'s table: sample score (target block's), then the true returns
    and the conditions' round trip where the file has them, and for the top block the share above own condition."""
    parts = [f"{v['sample_score']:.0f} ({_num(v['target_block_score'])})"]
    if "sample_true_return" in v:
        parts.append(f"{v['sample_true_return']:.0f} ({_num(v['target_block_true_return'])})")
    if "condition_round_trip_true_return" in v:
        parts.append(f"conditions' round trip {v['condition_round_trip_true_return']:.0f}")
    if v["target_block_score"] is None and "samples_above_condition" in v:
        parts.append(f"above own condition {v['samples_above_condition']:.0%}, max {v['sample_true_return_max']:.0f}"
                     f" (conditions' {v['condition_true_return_max']:.0f})")
    return "; ".join(parts)


def _summary_rows(path: Path, rec: dict, *, header: bool) -> list[str]:
    """:func:`summarize`'s rows of one results file (with the table's header when ``header``)."""
    rows = []
    for ev in rec["evaluations"]:
        per = ev["per_condition_block"]
        if header and not rows:
            rows = ["| file | diffuser steps | Spearman(condition block, sample score / true return) | "
                    + " | ".join(f"B{k} → sample score (B{int(k) + 1} mean); true return"
                                 if v["target_block_score"] is not None else f"B{k} (top: no target) → sample"
                                 for k, v in per.items()) + " |",
                    "|---|---|---|" + "---|" * len(per)]
        true_rho = ev.get("spearman_sample_true_return_vs_condition_block")
        rows.append(f"| {path.stem} | {ev['step']} | {ev['spearman_sample_score_vs_condition_block']:+.2f} / "
                    + ("—" if true_rho is None else f"{true_rho:+.2f}") + " | "
                    + " | ".join(_summary_cell(v) for v in per.values()) + " |")
    return rows


def plot_conditioning(paths: list[Path], out: Path) -> Path:
    """One panel per results file: each condition block's mean sample true return against the diffuser's training
    step (solid), beside the mean true return of the block's conditions (dotted) and of the block the pairs taught
    it to reach (dashed; the top block has none). A diffuser that follows its condition lifts every solid line to
    its dashed one; the flow's maximum can rise only where a top-block line passes its dotted one."""
    import matplotlib.pyplot as plt

    from torchrl_ftb.analysis import save_figure

    records = [json.loads(Path(p).read_text()) for p in paths]
    for path, rec in zip(paths, records):
        evs = rec.get("evaluations") or []
        if not evs or "sample_true_return" not in next(iter(evs[0]["per_condition_block"].values()), {}):
            raise ValueError(f"{path}: no evaluation with true returns to plot (run the bench with a reward oracle)")
    fig, axes = plt.subplots(1, len(records), figsize=(5.0 * len(records), 3.6), squeeze=False)
    for ax, path, rec in zip(axes[0], paths, records):
        evs = rec["evaluations"]
        steps = [ev["step"] for ev in evs]
        for i, block in enumerate(evs[-1]["per_condition_block"]):
            color = f"C{i}"
            rows = [ev["per_condition_block"][block] for ev in evs]
            ax.plot(steps, [r["sample_true_return"] for r in rows], "o-", color=color, label=f"B{block} samples")
            ax.axhline(rows[-1]["condition_true_return"], color=color, ls=":", lw=1)
            if rows[-1]["target_block_true_return"] is not None:
                ax.axhline(rows[-1]["target_block_true_return"], color=color, ls="--", lw=1)
        ax.set_title(Path(path).stem, fontsize=8)
        ax.set_xlabel("diffuser training step")
        ax.set_ylabel("true return (mean over the block's conditions)")
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0),
                       title="dotted: conditions, dashed: target block", title_fontsize=7)
    return save_figure(fig, out)


def main() -> None:
    parser = run_parser(__doc__)
    parser.add_argument("--steps", type=int, help="total diffuser steps to train up to")
    parser.add_argument("--eval-every", type=int, default=1500)
    parser.add_argument("--per-block", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=None,
                        help="true returns with the stop-rule fill to this many steps (Meta-World: 500); default plain")
    parser.add_argument("--streak", type=int, default=None,
                        help="with --horizon: cut samples where this many consecutive successes would end them (25)")
    parser.add_argument("--top-block", action="store_true",
                        help="also condition on the top block (the flow's top-k; no target block above it)")
    parser.add_argument("--sampler", default=None)
    parser.add_argument("--sample-steps", type=int, default=None)
    parser.add_argument("--guidance", type=float, default=None)
    parser.add_argument("--strength", type=float, default=1.0,
                        help="< 1: sample SDEdit edits of each condition (the recipe's diffuser.strength)")
    parser.add_argument("--score-guidance", type=float, default=0.0,
                        help="lambda of the recipe's diffuser.score_guidance: each sampler step also climbs the run's "
                             "s_psi (dataset-normalised); 0: none")
    parser.add_argument("--inpaint-start", action="store_true",
                        help="hold each sample's first observation at its condition's (diffuser.inpaint_start)")
    parser.add_argument("--work-dir", type=Path, default=None,
                        help="default: <run-dir>/conditioning_bench[_<preset>]")
    parser.add_argument("--preset", default=None,
                        help="train a FRESH diffuser of this preset (cpu | paper) on the run's pairs instead of "
                             "continuing the run's own (with its preset's batch size and lr)")
    parser.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE",
                        help="with --preset: model-field overrides of the fresh diffuser (YAML values), "
                             "e.g. concat_condition=true")
    parser.add_argument("--stride", type=int, default=1,
                        help="with --preset: the fresh diffuser models every STRIDE-th step (pairs and conditions "
                             "coarsened, samples refined back to the data's horizon before scoring)")
    parser.add_argument("--pairs", default="blocks", choices=("blocks", "copy"),
                        help="blocks: the run's adjacent-block pairs (FTB); copy: target = condition")
    parser.add_argument("--pair-weights", type=_weights, default=None, metavar="W0,W1,...",
                        help="with --preset and block pairs: weights of the transitions k -> k+1 (K - 1 of them, "
                             "e.g. 0,0,1,1: only pairs into the top two of 5 blocks); default uniform (the paper's)")
    parser.add_argument("--pair-neighbours", type=int, default=None, metavar="M",
                        help="with --preset and block pairs: pair each condition with one of the M next-block "
                             "trajectories that start nearest to it (BlockPairSampler(neighbours=M)); default the "
                             "run's own diffuser.pair_neighbours")
    parser.add_argument("--hold", action="store_true",
                        help="with --preset: train on and condition on trajectories held at their last step to the "
                             "full horizon (torchrl_ftb.data.hold_last_step: no padding, no length to generate); "
                             "the samples are cut again by --streak's stop rule")
    parser.add_argument("--device", default=None, help="default: cuda if available, else cpu")
    parser.add_argument("--autocast-bf16", action="store_true", help="bf16 autocast in training and sampling")
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="stop training after this much wall time (evaluates once more, then exits)")
    parser.add_argument("--plot", type=Path, default=None,
                        help="with --summarize: also plot the files' sample true return per block (PNG)")
    args = parse_run_args(parser, summarize, plot_conditioning)
    if args is None:
        return
    if args.plot is not None:
        parser.error("--plot goes with --summarize FILES (it plots saved results)")
    if args.steps is None:
        parser.error("--steps is required with --run-dir")
    if not (math.isfinite(args.score_guidance) and args.score_guidance >= 0.0):
        parser.error(f"--score-guidance must be a finite number >= 0, got {args.score_guidance}")
    if args.stride > 1 and args.score_guidance:
        parser.error("--score-guidance reads s_psi on the model's own trajectories; not with --stride")
    if not 0.0 < args.strength <= 1.0:
        parser.error(f"--strength must be in (0, 1], got {args.strength}")
    if args.stride > 1 and (args.strength < 1.0 or args.inpaint_start):
        parser.error("--strength < 1 and --inpaint-start edit the condition at the model's own resolution; "
                     "not with --stride")
    if args.stride > 1 and args.preset is None:
        parser.error("--stride needs --preset (a fresh diffuser on the coarsened trajectories)")
    if args.override and args.preset is None:
        parser.error("--override KEY=VALUE needs --preset (a fresh diffuser)")
    if args.hold and (args.preset is None or args.streak is None):
        parser.error("--hold needs --preset (a fresh diffuser on held trajectories) and --streak (the stop rule "
                     "that cuts the held samples)")
    if args.pair_weights is not None and (args.preset is None or args.pairs != "blocks"):
        parser.error("--pair-weights needs --preset and block pairs (a fresh diffuser on reweighted pairs)")
    if args.pair_neighbours is not None and (args.preset is None or args.pairs != "blocks"):
        parser.error("--pair-neighbours needs --preset and block pairs (a fresh diffuser on start-matched pairs)")
    try:
        overrides = parse_overrides(args.override)
    except ValueError as err:
        parser.error(f"--override: {err}")
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    run = args.run_dir
    if args.streak is not None and args.horizon is None:
        parser.error("--streak needs --horizon (the stop-rule cut comes before the fill)")
    cfg, trajs, returns = load_run(run, with_returns=True, horizon=args.horizon)
    if args.hold:  # the returns stay the recorded episodes' (the conditions' true value)
        trajs = hold_last_step(trajs)
    name = str(cfg.env.name)
    reward_fn = true_reward_fn(name, with_success=args.streak is not None)
    sampler, sample_steps, guidance = sampling_settings(cfg, sampler=args.sampler, steps=args.sample_steps,
                                                        guidance=args.guidance)
    if args.preset is not None:  # a fresh model: its own preset's training numbers
        train = get_preset(args.preset)["train"]
        batch_size, lr, clip = int(train["batch_size"]), float(train["lr"]), train.get("grad_clip")
    else:
        train = get_preset(str(cfg.diffuser.preset))["train"]
        batch_size = int(cfg.diffuser.batch_size or train["batch_size"])
        lr = float(cfg.diffuser.lr or train["lr"])
        clip = train.get("grad_clip") if cfg.diffuser.grad_clip == "preset" else cfg.diffuser.grad_clip

    work = args.work_dir or run / ("conditioning_bench" + ("_copy" if args.pairs == "copy" else "")
                                   + (f"_{args.preset}" if args.preset else "")
                                   + "".join(f"_{o.replace('=', '-')}" for o in args.override)
                                   + (f"_stride{args.stride}" if args.stride > 1 else "")
                                   + ("_w" + "-".join(f"{w:g}" for w in args.pair_weights) if args.pair_weights else "")
                                   + (f"_nn{args.pair_neighbours}" if args.pair_neighbours is not None else "")
                                   + ("_hold" if args.hold else ""))
    work.mkdir(parents=True, exist_ok=True)
    ckpt = work / "diffuser_last.pt"
    blocks = torch.load(run / "checkpoints" / "blocks.pt", weights_only=True)
    scores, ids = blocks["scores"].double(), blocks["block_ids"]
    model = load_score_model(run / "checkpoints" / "score_model.pt")
    # what the diffuser models: the trajectories, or every stride-th step of them (model, pairs, conditions)
    coarse = coarsen_trajectories(trajs, args.stride).contiguous() if args.stride > 1 else trajs
    if ckpt.exists():
        diffuser = load_diffuser(ckpt)
        if args.preset is not None and diffuser.horizon != coarse.batch_size[1]:
            parser.error(f"{ckpt}: a diffuser of horizon {diffuser.horizon}, not this --stride {args.stride}'s "
                         f"{coarse.batch_size[1]}; use another --work-dir")
    elif args.preset is not None:
        torch.manual_seed(int(cfg.seed))  # a fresh model's initial weights, as the recipe seeds them
        if cfg.diffuser.get("observation_structure") and args.stride > 1:
            parser.error("--stride with observation_structure: a coarse step's stacked frame is not its "
                         "predecessor's (the structure holds at stride 1 only)")
        if cfg.diffuser.get("observation_structure"):  # as the run's own diffuser (the recipe's rule)
            overrides = {**observation_layout(name), **overrides}
        diffuser = make_diffuser(args.preset, obs_dim=trajs["observation"].shape[-1],
                                 action_dim=trajs["action"].shape[-1], horizon=coarse.batch_size[1], data=coarse,
                                 **overrides)
    else:  # never touch the run's own checkpoint
        shutil.copy2(run / "checkpoints" / "diffuser" / "diffuser_last.pt", ckpt)
        diffuser = load_diffuser(ckpt)
    diffuser.to(device)
    if diffuser.score_condition:  # conditions (evaluation, copy pairs) carry their normalised score
        trajs, coarse = with_normalized_scores(trajs, scores), with_normalized_scores(coarse, scores)
    neighbours = args.pair_neighbours if args.pair_neighbours is not None else cfg.diffuser.get("pair_neighbours")
    top_pairs = bool(cfg.diffuser.get("top_block_pairs", False))  # the run's own pairing (diffuser.top_block_pairs)
    if args.pairs == "copy":
        copy_gen = torch.Generator().manual_seed(int(cfg.seed))

        def buffer() -> TensorDict:  # a fresh draw after a resume: a diagnostic, not a training recipe
            picked = coarse[torch.randint(0, coarse.batch_size[0], (batch_size,), generator=copy_gen)]
            return TensorDict({"condition": picked, "target": picked}, batch_size=[batch_size])
    else:
        # every key of trajs: observation, action, mask (+ the normalised score attached above); the run's
        # own pairing (diffuser.pair_neighbours) unless --pair-neighbours
        try:
            buffer = make_block_pair_buffer(coarse, ids, batch_size=batch_size, seed=int(cfg.seed), keys=None,
                                            neighbours=neighbours, block_weights=args.pair_weights,
                                            top_block_scores=scores if top_pairs else None)
        except ValueError as err:  # e.g. --pair-weights of another block count than the run's
            parser.error(f"{run / 'checkpoints' / 'blocks.pt'}: {err}")
    tag = f"-{args.tag}" if args.tag else ""
    # what the work dir's checkpoint trained on travels with it (a resume must not change it)
    data_file = work / "training_data.json"
    training_data = {"pair_weights": args.pair_weights, "hold": args.hold, "pair_neighbours": neighbours,
                     "top_block_pairs": top_pairs}
    run_default = {"pair_weights": None, "hold": False, "pair_neighbours": cfg.diffuser.get("pair_neighbours"),
                   "top_block_pairs": top_pairs}
    # files written before a field existed trained with its default
    trained_on = ({**run_default, **json.loads(data_file.read_text())} if data_file.exists()
                  else run_default if ckpt.exists() else training_data)
    if trained_on != training_data:
        parser.error(f"{work}: its diffuser trained on {trained_on}, not {training_data}; use another --work-dir")
    write_json(data_file, training_data)
    out = ROOT / "bench" / "results" / "diffuser_conditioning" / f"{name}-{run.name}{tag}.json"
    record = {**run_record(config={**vars(args), "run_dir": str(run), "sampler": sampler,
                                   "sample_steps": int(sample_steps), "guidance": float(guidance),
                                   "batch_size": batch_size, "lr": lr, "grad_clip": clip, "device": str(device),
                                   "diffuser_config": diffuser.config}),
              "evaluations": []}
    step = int(torch.load(ckpt, weights_only=True)["step"]) if ckpt.exists() else 0
    started = time.time()
    while True:
        t0 = time.time()
        ev = evaluate(diffuser, model, trajs, scores, ids, per_block=args.per_block, sampler=sampler,
                      steps=int(sample_steps), guidance=float(guidance), seed=int(cfg.seed), returns=returns,
                      reward_fn=reward_fn, autocast_bf16=args.autocast_bf16, top_block=args.top_block,
                      horizon=args.horizon, streak=args.streak, stride=args.stride, strength=args.strength,
                      inpaint_start=args.inpaint_start, score_guidance=args.score_guidance)
        ev.update(step=step, eval_seconds=round(time.time() - t0, 1))
        record["evaluations"].append(ev)
        write_json(out, record)
        print(f"step {step}: spearman(block) {ev['spearman_sample_score_vs_condition_block']:.3f} "
              f"spearman(score) {ev['spearman_sample_score_vs_condition_score']:.3f} "
              + " ".join(f"B{k}:{v['sample_score']:.0f}/{_num(v['target_block_score'])}"
                         for k, v in ev["per_condition_block"].items())
              + f" trajectory gap own/other {ev['trajectory_gap']['own']:.2f}/{ev['trajectory_gap']['other']:.2f},"
              + " start gap own/other " + ", ".join(f"{k.removesuffix('_own')} {v:.2f}/{ev['start_gap'][k[:-4] + '_other']:.2f}"
                                                    for k, v in ev["start_gap"].items() if k.endswith("_own")), flush=True)
        out_of_time = args.max_minutes is not None and time.time() - started > 60 * args.max_minutes
        if step >= args.steps or out_of_time:
            break
        nxt = min(args.steps, step + args.eval_every)
        res = train_diffuser(diffuser, buffer, steps=nxt, lr=lr, grad_clip=None if clip is None else float(clip),
                             checkpoint_dir=work, checkpoint_every=500, resume=True, progress=False,
                             seed=int(cfg.seed), device=device, autocast_bf16=args.autocast_bf16)
        step = int(res["step"])
        record.setdefault("train", []).append({"to_step": step, "wall_time_s": round(res["wall_time_s"], 1),
                                               "final_loss": res["final_loss"]})
    print(f"-> {out}")


if __name__ == "__main__":
    main()
