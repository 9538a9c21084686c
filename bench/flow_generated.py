"""What did the flow put into the final set? One row per generated trajectory of an FTB run.

Reads a finished run of ``recipes/ftb_offline.py`` (its ``checkpoints/flow.pt``) and reports,
for every generated trajectory the flow accepted, its length, the flow step that produced it,
its true return as the flow recorded it, and for Meta-World two dynamics proxies in metres --
whether a high "true return" belongs to a physically consistent trajectory: the frame-stack
error (:func:`torchrl_ftb.envs.metaworld_frame_stack_error`; 0 for real data, and 0 by
construction with ``diffuser.observation_structure=true``) and the residual of a linear
one-step hand model fitted on the run's original top-k
(:func:`torchrl_ftb.envs.metaworld_hand_model_error`; about 1 mm on real data). No sampling, no training. JSON to
``bench/results/flow_generated.json`` (command, config, commit, machine).

With ``--horizon H`` it also re-scores the original top-k and the final set with the
ground-truth oracle (:func:`torchrl_ftb.flow.masked_true_returns`) under two return definitions,
the plain sum and the stop-rule fill to ``H`` steps (a success ends a Meta-World episode, so
the plain sum pays a slow success more than a fast one), and the same again with the final
set's generated trajectories that exceed ``--max-frame-stack-error`` or
``--max-hand-model-error`` replaced by the originals they displaced: the improvement target (issue #5) on runs made
before the recipe reported the fill (``flow.true_return_horizon``).

Usage::

    python bench/flow_generated.py --run-dirs outputs/table1_v2/sweep-into-v3/return/ftb/seed1
    python bench/flow_generated.py --run-dirs RUN... --horizon 500 --out bench/results/flow_improvement.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.envs import (fit_metaworld_hand_model, metaworld_frame_stack_error,  # noqa: E402
                              metaworld_hand_model_error, true_reward_fn)
from torchrl_ftb.flow import masked_true_returns, return_summary  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def physically_invalid(rows: list[dict], *, max_frame_stack_error: float, max_hand_model_error: float) -> torch.Tensor:
    """``[n_generated]`` True where a generated trajectory breaks the frame stack or the hand model
    by more than the limits (metres; rows without a check -- non-Meta-World -- count as valid)."""
    def over(key: str, limit: float) -> torch.Tensor:
        return torch.tensor([r.get(key) is not None and r[key] > limit for r in rows], dtype=torch.bool)
    return over("frame_stack_error_m", max_frame_stack_error) | over("hand_model_error_m", max_hand_model_error)


def oracle_improvement(task: str, original: TensorDict, final: TensorDict, generated: torch.Tensor,
                       invalid: torch.Tensor, *, horizon: int) -> dict[str, dict[str, float]]:
    """Oracle mean/max true return, original top-k vs final set: plain, filled, and both on the final
    set with the physically invalid generated trajectories (``invalid``, one flag per generated one)
    swapped back for the best originals it left out."""
    fn = true_reward_fn(task)
    before = masked_true_returns(original, fn, horizons=(None, horizon))  # [k, 2]: plain, filled
    after = masked_true_returns(final, fn, horizons=(None, horizon))
    bad = torch.zeros(final.batch_size[0], dtype=torch.bool)
    bad[generated.nonzero().squeeze(-1)] = invalid
    # the final set holds the best-scored originals (it is the top-k of the pool), so those it left out
    # are the tail of the score-sorted original top-k
    left_out = before[final.batch_size[0] - int(generated.sum()):]
    checked = torch.cat([after[~bad], left_out[: int(bad.sum())]], 0)
    out = {}
    for j, name in enumerate(("plain", f"filled_{horizon}")):
        for suffix, final_ret in (("", after), ("_physically_checked", checked)):
            out[name + suffix] = return_summary(before[:, j], final_ret[:, j])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "flow_generated.json")
    parser.add_argument("--horizon", type=int, default=None,
                        help="also report the oracle improvement, plain and with the stop-rule fill to this many steps")
    parser.add_argument("--max-frame-stack-error", type=float, default=0.02,
                        help="metres: generated trajectories above it count as physically invalid (data: 0)")
    parser.add_argument("--max-hand-model-error", type=float, default=0.01,
                        help="metres: generated trajectories whose hand path misses the linear one-step hand "
                             "model fitted on the original top-k by more count as physically invalid (data: ~1 mm)")
    args = parser.parse_args()
    record = {**run_record(config={"run_dirs": [str(r) for r in args.run_dirs], "horizon": args.horizon,
                                   "max_frame_stack_error": args.max_frame_stack_error,
                                   "max_hand_model_error": args.max_hand_model_error}), "runs": {}}
    for run in args.run_dirs:
        cfg = OmegaConf.load(run / "config.yaml")
        ckpt = torch.load(run / "checkpoints" / "flow.pt", weights_only=True)
        final = TensorDict(ckpt["trajectories"]["data"], batch_size=ckpt["trajectories"]["batch_size"])
        original = TensorDict(ckpt["original"]["data"], batch_size=ckpt["original"]["batch_size"])
        generated = ckpt["source_step"] > 0
        metaworld = original.get("observation").shape[-1] == 39
        # the hand model is fitted on the (real) original top-k; its residual there is the reference
        hand_w = fit_metaworld_hand_model(original) if metaworld else None
        rows = []
        if bool(generated.any()):
            gen = final[generated]
            none = [None] * gen.batch_size[0]
            stack = metaworld_frame_stack_error(gen).tolist() if metaworld else none
            hand = metaworld_hand_model_error(gen, hand_w).tolist() if metaworld else none
            true = ckpt.get("true_returns")
            for i, j in enumerate(generated.nonzero().squeeze(-1).tolist()):
                rows.append({"length": int(gen.get("mask")[i].sum()), "flow_step": int(ckpt["source_step"][j]),
                             "score": float(ckpt["scores"][j]),
                             "true_return": None if true is None else float(true[j]),
                             "frame_stack_error_m": stack[i], "hand_model_error_m": hand[i]})
        invalid = physically_invalid(rows, max_frame_stack_error=args.max_frame_stack_error,
                                     max_hand_model_error=args.max_hand_model_error)
        entry = record["runs"][str(run)] = {
            "env": str(cfg.env.name), "seed": int(cfg.seed), "teacher": str(cfg.labels.teacher),
            "top_k": int(cfg.flow.top_k), "observation_structure": bool(cfg.diffuser.get("observation_structure", False)),
            "hand_model_error_original_m": float(metaworld_hand_model_error(original, hand_w, pooled=True)) if metaworld else None,
            "generated_in_final_set": rows, "physically_invalid_in_final_set": int(invalid.sum())}
        if args.horizon is not None:
            entry["improvement"] = oracle_improvement(str(cfg.env.name), original, final, generated, invalid,
                                                      horizon=args.horizon)
            print("  " + "; ".join(f"{name}: mean {v['true_return_mean_before']:.0f} -> {v['true_return_mean_after']:.0f}, "
                                   f"max {v['true_return_max_before']:.0f} -> {v['true_return_max_after']:.0f}"
                                   for name, v in record["runs"][str(run)]["improvement"].items()))
        print(f"{cfg.env.name} seed {cfg.seed}: " + "; ".join(
            f"len {r['length']} return {r['true_return']:.0f} frame-stack {r['frame_stack_error_m']} "
            f"hand model {r['hand_model_error_m']}" for r in rows))
        write_json(args.out, record)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
