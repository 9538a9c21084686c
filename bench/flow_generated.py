"""What did the flow put into the final set? One row per generated trajectory of an FTB run.

Reads a finished run of ``recipes/ftb_offline.py`` (its ``checkpoints/flow.pt``) and reports,
for every generated trajectory the flow accepted, its length, the flow step that produced it,
its true return as the flow recorded it, and for Meta-World three dynamics proxies in metres --
whether a high "true return" belongs to a physically possible trajectory:

* the frame-stack error (:func:`torchrl_ftb.envs.metaworld_frame_stack_error`; 0 for real data,
  and 0 by construction with ``diffuser.observation_structure=true``);
* the residual of a linear one-step hand model fitted on the run's original top-k
  (:func:`torchrl_ftb.envs.metaworld_hand_model_error`; about 1 mm on real data);
* how far the object moves while the hand is out of reach
  (:func:`torchrl_ftb.envs.metaworld_contactless_object_path`; the reach and the limit come from
  the original top-k: no real trajectory there moves it further).

No sampling, no training. JSON to ``bench/results/flow_generated.json`` (command, config, commit,
machine).

With ``--horizon H`` it also re-scores the original top-k and the final set with the
ground-truth oracle (:func:`torchrl_ftb.flow.masked_true_returns`) under two return definitions,
the plain sum and the stop-rule fill to ``H`` steps (a success ends a Meta-World episode, so
the plain sum pays a slow success more than a fast one) -- on Meta-World also the fill after cutting
each trajectory where the data's stop rule (25 consecutive successes) would have ended it, since
generated trajectories are not cut by it, and a generated one that ends early without that streak is
not filled there (no stop rule ended it) -- and the same again with the final
set's generated trajectories that fail any of the three checks replaced by the originals they
displaced: the improvement target (issue #5) on runs made before the recipe reported the fill
(``flow.true_return_horizon``).

Usage::

    python bench/flow_generated.py --run-dirs outputs/table1_v2/sweep-into-v3/return/ftb/seed1
    python bench/flow_generated.py --run-dirs RUN... --horizon 500 --out bench/results/flow_improvement.json
    python bench/flow_generated.py --summarize bench/results/flow_improvement*.json   # Markdown table
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.analysis import metaworld_state_returns as metaworld_returns  # noqa: E402
from torchrl_ftb.envs import (METAWORLD_PHYSICS_PROXIES, env_kind, fit_metaworld_contact_reach,  # noqa: E402
                              fit_metaworld_hand_model, metaworld_contactless_object_path,
                              metaworld_hand_model_error, metaworld_physics_errors,
                              true_reward_fn)
from torchrl_ftb.flow import masked_true_returns, return_summary  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def physics_reference(original: TensorDict, *, contact_quantile: float) -> dict:
    """The proxies' calibration on the real original top-k (empty off Meta-World): the hand model, its
    residual there, the hand's reach and the furthest any original moves its object out of reach."""
    if original.get("observation").shape[-1] != 39:
        return {}
    hand_w = fit_metaworld_hand_model(original)
    reach = fit_metaworld_contact_reach(original, quantile=contact_quantile)
    return {"hand_weights": hand_w,
            "hand_model_error_original_m": float(metaworld_hand_model_error(original, hand_w, pooled=True)),
            "contact_reach_m": reach,
            "contactless_object_path_original_max_m": float(metaworld_contactless_object_path(original, reach).max())}


def generated_rows(ckpt: dict, final: TensorDict, generated: torch.Tensor, ref: dict) -> list[dict]:
    """One row per generated trajectory of the final set: length, flow step, score, recorded true return,
    and the three physics proxies as ``<name>_m`` (metres; ``None`` off Meta-World)."""
    if not bool(generated.any()):
        return []
    gen = final[generated]
    proxies = {f"{key}_m": [None] * gen.batch_size[0] for key in METAWORLD_PHYSICS_PROXIES}
    if ref:
        errors = metaworld_physics_errors(gen, hand_weights=ref["hand_weights"], reach=ref["contact_reach_m"])
        proxies = {f"{key}_m": errors[key].tolist() for key in METAWORLD_PHYSICS_PROXIES}
    true = ckpt.get("true_returns")
    return [{"length": int(gen.get("mask")[i].sum()), "flow_step": int(ckpt["source_step"][j]),
             "score": float(ckpt["scores"][j]), "true_return": None if true is None else float(true[j]),
             **{key: values[i] for key, values in proxies.items()}}
            for i, j in enumerate(generated.nonzero().squeeze(-1).tolist())]


def proxy_failures(rows: list[dict], *, max_frame_stack_error: float, max_hand_model_error: float,
                   max_contactless_object_path: float = float("inf")) -> dict[str, torch.Tensor]:
    """Per proxy, ``[n_generated]`` True where a generated trajectory exceeds its limit (metres; rows
    without a check -- non-Meta-World -- pass)."""
    limits = dict(zip(METAWORLD_PHYSICS_PROXIES,
                      (max_frame_stack_error, max_hand_model_error, max_contactless_object_path)))
    return {key: torch.tensor([r.get(f"{key}_m") is not None and r[f"{key}_m"] > limit for r in rows], dtype=torch.bool)
            for key, limit in limits.items()}


def physically_invalid(rows: list[dict], **limits: float) -> torch.Tensor:
    """``[n_generated]`` True where a generated trajectory fails any proxy (:func:`proxy_failures`)."""
    return torch.stack(list(proxy_failures(rows, **limits).values())).any(0)


def oracle_improvement(task: str, original: TensorDict, final: TensorDict, generated: torch.Tensor,
                       invalid: torch.Tensor, *, horizon: int) -> dict[str, dict[str, float]]:
    """Oracle mean/max true return, original top-k vs final set: plain, filled, and both on the final
    set with the physically invalid generated trajectories (``invalid``, one flag per generated one)
    swapped back for the best originals it left out."""
    if env_kind(task) == "metaworld":
        before, after = metaworld_returns(task, original, horizon=horizon), metaworld_returns(task, final, horizon=horizon)
        names = ("plain", f"filled_{horizon}", f"filled_{horizon}_stop_rule")
    else:
        fn = true_reward_fn(task)
        before = masked_true_returns(original, fn, horizons=(None, horizon))  # [k, 2]: plain, filled
        after = masked_true_returns(final, fn, horizons=(None, horizon))
        names = ("plain", f"filled_{horizon}")
    bad = torch.zeros(final.batch_size[0], dtype=torch.bool)
    bad[generated.nonzero().squeeze(-1)] = invalid
    # the final set holds the best-scored originals (it is the top-k of the pool), so those it left out
    # are the tail of the score-sorted original top-k
    left_out = before[final.batch_size[0] - int(generated.sum()):]
    checked = torch.cat([after[~bad], left_out[: int(bad.sum())]], 0)
    out = {}
    for j, name in enumerate(names):
        for suffix, final_ret in (("", after), ("_physically_checked", checked)):
            out[name + suffix] = return_summary(before[:, j], final_ret[:, j])
    return out


def _before_after(v: dict, stat: str) -> str:
    return f"{v[f'true_return_{stat}_before']:.0f} → {v[f'true_return_{stat}_after']:.0f}"


def summary_table(records: dict[str, dict]) -> str:
    """Markdown, one row per run of the given ``--horizon`` results: the final set's generated trajectories,
    how many fail which proxy, and the oracle mean / max before → after, as flowed and with those swapped back."""
    rows = ["| file | task | seed | diffuser | generated in final set | fail: frame stack / hand model / contact "
            "| plain mean | plain max | filled mean | filled max | filled mean, stop rule | filled max, stop rule |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, record in records.items():
        limits = record["config"]
        for entry in record["runs"].values():
            gen, imp = entry["generated_in_final_set"], entry.get("improvement")
            if imp is None:
                continue
            fails = [int(f.sum()) for f in proxy_failures(
                gen, max_frame_stack_error=limits["max_frame_stack_error"],
                max_hand_model_error=limits["max_hand_model_error"],
                max_contactless_object_path=entry.get("contactless_object_path_original_max_m") or float("inf")).values()]
            filled = next(k for k in imp if k.startswith("filled_") and not k.endswith("_checked"))
            cols = [f"{_before_after(imp[base], stat)} "
                    f"({imp[base + '_physically_checked'][f'true_return_{stat}_after']:.0f} checked)"
                    if base in imp else "—"
                    for base in ("plain", filled, filled + "_stop_rule") for stat in ("mean", "max")]
            rows.append(f"| {name} | {entry['env']} | {entry['seed']} | "
                        f"{'structure' if entry.get('observation_structure') else 'raw'} | {len(gen)} | "
                        f"{' / '.join(map(str, fails))} (any: {entry['physically_invalid_in_final_set']}) | "
                        + " | ".join(cols) + " |")
    return "\n".join(rows)


def require_finished_runs(parser: argparse.ArgumentParser, run_dirs: list[Path]) -> None:
    """A clear command-line error, before any work, for a run directory without a finished flow stage."""
    for run in run_dirs:
        missing = [name for name in ("config.yaml", "checkpoints/flow.pt") if not (run / name).is_file()]
        if missing:
            parser.error(f"{run}: not a finished FTB run directory (no {' or '.join(missing)})")


def runs_from_args(parser: argparse.ArgumentParser, summarize_fn: Callable[[list[Path]], str]) -> argparse.Namespace | None:
    """Parse a bench over finished runs (``--run-dirs``, ``--summarize``): with ``--summarize`` print
    ``summarize_fn(files)`` and return None; else require ``--run-dirs``, each a finished run directory."""
    args = parser.parse_args()
    if args.summarize:
        print(summarize_fn(args.summarize))
        return None
    if not args.run_dirs:
        parser.error("give --run-dirs (or --summarize)")
    require_finished_runs(parser, args.run_dirs)
    return args


def measure_runs(run_dirs: list[Path], out: Path, config: dict, measure: Callable[[Path], dict],
                 describe: Callable[[Path, dict], str]) -> dict:
    """``measure(run)`` for each run directory, printing ``describe(run, entry)``; the results file (command,
    config, commit, machine, ``runs``) is rewritten after every run, so a stopped job keeps what it finished."""
    record = {**run_record(config={"run_dirs": [str(r) for r in run_dirs], **config}), "runs": {}}
    for run in run_dirs:
        entry = record["runs"][str(run)] = measure(run)
        print(describe(run, entry))
        write_json(out, record)
    print(f"-> {out}")
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path)
    parser.add_argument("--summarize", nargs="+", type=Path, help="print the Markdown table of these results files")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "flow_generated.json")
    parser.add_argument("--horizon", type=int, default=None,
                        help="also report the oracle improvement, plain and with the stop-rule fill to this many steps")
    parser.add_argument("--max-frame-stack-error", type=float, default=0.02,
                        help="metres: generated trajectories above it count as physically invalid (data: 0)")
    parser.add_argument("--max-hand-model-error", type=float, default=0.01,
                        help="metres: generated trajectories whose hand path misses the linear one-step hand "
                             "model fitted on the original top-k by more count as physically invalid (data: ~1 mm)")
    parser.add_argument("--contact-quantile", type=float, default=0.99,
                        help="the hand 'reaches' the object within the hand-object distance that holds this share of "
                             "the original top-k's object motion; generated trajectories that move the object beyond "
                             "reach further than any original does count as physically invalid")
    args = runs_from_args(parser, lambda files: summary_table({path.stem: json.loads(path.read_text())
                                                                for path in files}))
    if args is None:
        return
    measure_runs(args.run_dirs, args.out,
                 {"horizon": args.horizon, "max_frame_stack_error": args.max_frame_stack_error,
                  "max_hand_model_error": args.max_hand_model_error, "contact_quantile": args.contact_quantile},
                 lambda run: measure_run(run, horizon=args.horizon, max_frame_stack_error=args.max_frame_stack_error,
                                         max_hand_model_error=args.max_hand_model_error,
                                         contact_quantile=args.contact_quantile),
                 describe_run)


def load_flow_sets(run: Path) -> tuple[dict, TensorDict, TensorDict, torch.Tensor]:
    """``(checkpoint, final set, original top-k, generated flags [k])`` of a finished run's ``checkpoints/flow.pt``."""
    ckpt = torch.load(run / "checkpoints" / "flow.pt", weights_only=True)
    final = TensorDict(ckpt["trajectories"]["data"], batch_size=ckpt["trajectories"]["batch_size"])
    original = TensorDict(ckpt["original"]["data"], batch_size=ckpt["original"]["batch_size"])
    return ckpt, final, original, ckpt["source_step"] > 0


def measure_run(run: Path, *, horizon: int | None, max_frame_stack_error: float, max_hand_model_error: float,
                contact_quantile: float) -> dict:
    """One run's entry: the physics proxies of every generated trajectory in its final set and, with
    ``horizon``, the oracle improvement (plain, filled, and with the physically invalid samples replaced)."""
    cfg = OmegaConf.load(run / "config.yaml")
    ckpt, final, original, generated = load_flow_sets(run)
    ref = physics_reference(original, contact_quantile=contact_quantile)
    rows = generated_rows(ckpt, final, generated, ref)
    invalid = physically_invalid(rows, max_frame_stack_error=max_frame_stack_error,
                                 max_hand_model_error=max_hand_model_error,
                                 max_contactless_object_path=ref.get("contactless_object_path_original_max_m",
                                                                     float("inf")))
    entry = {"env": str(cfg.env.name), "seed": int(cfg.seed), "teacher": str(cfg.labels.teacher),
             "top_k": int(cfg.flow.top_k),
             "observation_structure": bool(cfg.diffuser.get("observation_structure", False)),
             **{k: v for k, v in ref.items() if k != "hand_weights"},
             "generated_in_final_set": rows, "physically_invalid_in_final_set": int(invalid.sum())}
    if horizon is not None:
        entry["improvement"] = oracle_improvement(str(cfg.env.name), original, final, generated, invalid,
                                                  horizon=horizon)
    return entry


def describe_run(run: Path, entry: dict) -> str:
    """The printed line(s) of one measured run."""
    lines = []
    if "improvement" in entry:
        lines.append("  " + "; ".join(f"{name}: mean {v['true_return_mean_before']:.0f} -> "
                                      f"{v['true_return_mean_after']:.0f}, max {v['true_return_max_before']:.0f} -> "
                                      f"{v['true_return_max_after']:.0f}" for name, v in entry["improvement"].items()))
    lines.append(f"{entry['env']} seed {entry['seed']}: " + "; ".join(
        f"len {r['length']} return {r['true_return']:.0f} frame-stack {r['frame_stack_error_m']} "
        f"hand model {r['hand_model_error_m']} contactless {r['contactless_object_path_m']}"
        for r in entry["generated_in_final_set"]))
    return "\n".join(lines)


if __name__ == "__main__":
    main()
