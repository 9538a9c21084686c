"""Does the trajectory diffuser follow its condition, and after how many training steps?

FTB's diffuser is trained on pairs (tau_0 in block k, tau_1 in block k + 1): a sample
conditioned on a block-k trajectory should look like a block-(k + 1) one. This bench copies
the diffuser checkpoint of an FTB run (``recipes/ftb_offline.py``), continues its training on
the run's own block pairs (same buffer, optimiser state and RNG: ``train_diffuser(resume=True)``)
and, every ``--eval-every`` steps, samples one trajectory for each of ``--per-block``
conditions from every block but the last, scoring the samples with the run's score model.
Reported per evaluation: the Spearman correlation of the sample's score with the condition's
block (an unconditional model gives ~0), the mean sample score per condition block next to
the dataset's mean score of the block the pairs taught it to produce (k + 1), and the mean
generated length. JSON to ``bench/results/diffuser_conditioning/<task>-<tag>.json`` after
every evaluation (partial results survive a kill).

Usage::

    python bench/diffuser_conditioning.py --run-dir outputs/exp/bp-norm-gc --steps 4500 --eval-every 1500
    python bench/diffuser_conditioning.py --summarize bench/results/diffuser_conditioning/*.json
"""
from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_diagnostics import (  # noqa: E402
    load_run, parse_run_args, run_parser, sampling_settings, spearman,
)

from torchrl_ftb.diffusion import get_preset, load_diffuser, train_diffuser  # noqa: E402
from torchrl_ftb.preference import load_score_model, make_block_pair_buffer, score_trajectories  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def evaluate(diffuser, model, trajs, scores, ids, *, per_block: int, sampler: str, steps: int, guidance: float,
             seed: int) -> dict:
    """Condition-following statistics of one model state (see module docstring)."""
    gen = torch.Generator().manual_seed(seed)
    num_blocks = int(ids.max()) + 1
    picks, blocks = [], []
    for k in range(num_blocks - 1):
        members = (ids == k).nonzero().squeeze(-1)
        order = torch.randperm(members.numel(), generator=torch.Generator().manual_seed(seed + k))
        chosen = members[order[:per_block]]
        picks.append(chosen)
        blocks += [k] * chosen.numel()
    idx = torch.cat(picks)
    blocks = torch.tensor(blocks)
    cond = trajs[idx]
    sample = diffuser.generate(cond, sampler=sampler, steps=steps, guidance=guidance, generator=gen)
    s_new = score_trajectories(model, sample).double()
    length = sample["mask"].sum(-1).double()
    per = {}
    for k in range(num_blocks - 1):
        m = blocks == k
        per[str(k + 1)] = {"condition_score": float(scores[idx[m]].mean()), "sample_score": float(s_new[m].mean()),
                           "target_block_score": float(scores[ids == k + 1].mean()),
                           "sample_length": float(length[m].mean()),
                           "target_block_length": float(trajs["mask"][ids == k + 1].sum(-1).double().mean())}
    return {"spearman_sample_score_vs_condition_block": spearman(blocks.double(), s_new),
            "spearman_sample_score_vs_condition_score": spearman(scores[idx], s_new),
            "per_condition_block": per, "num_conditions": int(idx.numel())}


def summarize(paths: list[Path]) -> str:
    """Markdown table of saved results: one row per (file, evaluation)."""
    rows = []
    for path in paths:
        rec = json.loads(path.read_text())
        for ev in rec["evaluations"]:
            per = ev["per_condition_block"]
            if not rows:
                rows = ["| file | diffuser steps | Spearman(sample score, condition block) | "
                        + " | ".join(f"B{k} → sample (B{int(k) + 1} mean)" for k in per) + " |",
                        "|---|---|---|" + "---|" * len(per)]
            rows.append(f"| {path.stem} | {ev['step']} | {ev['spearman_sample_score_vs_condition_block']:+.2f} | "
                        + " | ".join(f"{v['sample_score']:.0f} ({v['target_block_score']:.0f})" for v in per.values())
                        + " |")
    return "\n".join(rows)


def main() -> None:
    parser = run_parser(__doc__)
    parser.add_argument("--steps", type=int, help="total diffuser steps to train up to")
    parser.add_argument("--eval-every", type=int, default=1500)
    parser.add_argument("--per-block", type=int, default=8)
    parser.add_argument("--sampler", default=None)
    parser.add_argument("--sample-steps", type=int, default=None)
    parser.add_argument("--guidance", type=float, default=None)
    parser.add_argument("--work-dir", type=Path, default=None, help="default: <run-dir>/conditioning_bench")
    args = parse_run_args(parser, summarize)
    if args is None:
        return
    if args.steps is None:
        parser.error("--steps is required with --run-dir")
    run = args.run_dir
    cfg, trajs = load_run(run)
    name = str(cfg.env.name)
    sampler, sample_steps, guidance = sampling_settings(cfg, sampler=args.sampler, steps=args.sample_steps,
                                                        guidance=args.guidance)
    train = get_preset(str(cfg.diffuser.preset))["train"]
    batch_size = int(cfg.diffuser.batch_size or train["batch_size"])
    lr = float(cfg.diffuser.lr or train["lr"])
    clip = train.get("grad_clip") if cfg.diffuser.grad_clip == "preset" else cfg.diffuser.grad_clip

    work = args.work_dir or run / "conditioning_bench"
    work.mkdir(parents=True, exist_ok=True)
    ckpt = work / "diffuser_last.pt"
    if not ckpt.exists():  # never touch the run's own checkpoint
        shutil.copy2(run / "checkpoints" / "diffuser" / "diffuser_last.pt", ckpt)
    blocks = torch.load(run / "checkpoints" / "blocks.pt", weights_only=True)
    scores, ids = blocks["scores"].double(), blocks["block_ids"]
    model = load_score_model(run / "checkpoints" / "score_model.pt")
    diffuser = load_diffuser(ckpt)
    buffer = make_block_pair_buffer(trajs, ids, batch_size=batch_size, seed=int(cfg.seed))
    tag = f"-{args.tag}" if args.tag else ""
    out = ROOT / "bench" / "results" / "diffuser_conditioning" / f"{name}-{run.name}{tag}.json"
    record = {**run_record(config={**vars(args), "run_dir": str(run), "sampler": sampler,
                                   "sample_steps": int(sample_steps), "guidance": float(guidance),
                                   "batch_size": batch_size, "lr": lr, "grad_clip": clip,
                                   "diffuser_config": diffuser.config}),
              "evaluations": []}
    step = int(torch.load(ckpt, weights_only=True)["step"])
    while True:
        t0 = time.time()
        ev = evaluate(diffuser, model, trajs, scores, ids, per_block=args.per_block, sampler=sampler,
                      steps=int(sample_steps), guidance=float(guidance), seed=int(cfg.seed))
        ev.update(step=step, eval_seconds=round(time.time() - t0, 1))
        record["evaluations"].append(ev)
        write_json(out, record)
        print(f"step {step}: spearman(block) {ev['spearman_sample_score_vs_condition_block']:.3f} "
              f"spearman(score) {ev['spearman_sample_score_vs_condition_score']:.3f} "
              + " ".join(f"B{k}:{v['sample_score']:.0f}/{v['target_block_score']:.0f}"
                         for k, v in ev["per_condition_block"].items()), flush=True)
        if step >= args.steps:
            break
        nxt = min(args.steps, step + args.eval_every)
        res = train_diffuser(diffuser, buffer, steps=nxt, lr=lr, grad_clip=None if clip is None else float(clip),
                             checkpoint_dir=work, checkpoint_every=500, resume=True, progress=False,
                             seed=int(cfg.seed))
        step = int(res["step"])
        record.setdefault("train", []).append({"to_step": step, "wall_time_s": round(res["wall_time_s"], 1),
                                               "final_loss": res["final_loss"]})
    print(f"-> {out}")


if __name__ == "__main__":
    main()
