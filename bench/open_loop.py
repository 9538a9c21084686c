"""Do a run's generated trajectories do in the simulator what their states say? Open-loop replays.

The bench form of :func:`torchrl_ftb.analysis.open_loop_improvement` (the recipe runs the same on its own
final set, ``analysis.open_loop``; see that module for the method): for finished FTB run directories on
generated Meta-World data, replay every generated trajectory of the final set (``checkpoints/flow.pt``)
from its nearest dataset start, open loop, and compare the simulator's returns with the ones its states
claim, original top-k -> final set. On locomotion runs every trajectory of both sets is replayed from its own
first state (:func:`torchrl_ftb.analysis.locomotion_open_loop_improvement`), and the top-k's own actions are
replayed again with Gaussian noise added (``--action-noise``), to show how fragile open loop is on that data.
``--no-hold`` stops each replay after the sample's last action instead of holding still until the stop rule or
the time limit.

Usage::

    python bench/open_loop.py --run-dirs RUN [RUN ...] --horizon 500 --out bench/results/open_loop.json
    python bench/open_loop.py --summarize bench/results/open_loop_*.json bench/results/table1_v2_x/ftb__*.json

``--summarize`` prints one Markdown row per run of this bench's results files, or of table1 cell files whose
run had the recipe's ``analysis.open_loop`` (policy success then in the last column; a locomotion cell's reading,
:func:`torchrl_ftb.analysis.locomotion_open_loop_improvement`, with its D4RL-normalised score there).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from expert_headroom import load_metaworld_run  # noqa: E402
from flow_generated import load_flow_sets, measure_runs, runs_from_args  # noqa: E402

from torchrl_ftb.analysis import (  # noqa: E402
    ended_early,
    locomotion_open_loop_improvement,
    locomotion_replays,
    open_loop_improvement,
    summarize_samples,
)
from torchrl_ftb.envs import env_kind  # noqa: E402


def load_flow(run: Path) -> tuple:
    """``(cfg, data, meta, final, original, generated, original_rows)`` of a finished run directory: its
    dataset and the flow's final set and original top-k (``checkpoints/flow.pt``)."""
    cfg, data, meta = load_metaworld_run(run)
    ckpt, final, original, generated = load_flow_sets(run)
    return cfg, data, meta, final, original, generated, ckpt.get("original_indices")


def action_noise_replays(env_name: str, trajs, noise: list[float], *, seed: int = 0) -> list[dict]:
    """How fragile open loop is on this data: ``trajs``' own actions replayed from their own starts with Gaussian
    noise of each std added (then clipped to the action box): mean return and the share the env ends before the
    actions run out. One seeded standard-normal draw, scaled by each std (common random numbers: a row does not
    depend on which other stds are asked for)."""
    draw = torch.randn(trajs["action"].shape, generator=torch.Generator().manual_seed(seed))
    lengths = trajs["mask"].sum(-1)
    out = []
    for std in noise:
        noisy = trajs.select("observation", "action", "mask").clone()
        noisy["action"] = noisy["action"] + std * draw
        returns, episodes = locomotion_replays(env_name, noisy)
        early = [ended_early(ep, n) for ep, n in zip(episodes, lengths.tolist())]
        out.append({"action_noise_std": std, "return_mean": float(returns.mean()),
                    "return_max": float(returns.max()), "terminated_early": sum(early) / len(early)})
    return out


def locomotion_open_loop(run: Path, *, noise: list[float], progress: bool) -> dict:
    """:func:`torchrl_ftb.analysis.locomotion_open_loop_improvement` of a finished locomotion run's final set, and
    the top-k's own actions replayed with noise (:func:`action_noise_replays`) to calibrate it."""
    cfg = OmegaConf.load(run / "config.yaml")
    _, final, original, generated = load_flow_sets(run)
    name = str(cfg.env.name)
    out = locomotion_open_loop_improvement(final, original, generated, env_name=name, progress=progress)
    return {"env": name, "seed": int(cfg.seed), "top_k": int(original.batch_size[0]),
            "flow_filter": str(cfg.flow.get("filter", "score_model")), **out,
            "top_k_action_noise": action_noise_replays(name, original, noise, seed=int(cfg.seed))}


def open_loop(run: Path, *, horizon: int, progress: bool, hold: bool = True) -> dict:
    """:func:`torchrl_ftb.analysis.open_loop_improvement` of a finished run directory's final set."""
    cfg, data, meta, final, original, generated, rows = load_flow(run)
    out = open_loop_improvement(final, original, generated, data, meta, task=str(cfg.env.name),
                                horizon=horizon, original_rows=rows, hold=hold, progress=progress)
    return {"env": str(cfg.env.name), "seed": int(cfg.seed), "top_k": int(original.batch_size[0]),
            "flow_filter": str(cfg.flow.get("filter", "score_model")),
            "diffuser_strength": float(cfg.diffuser.get("strength", 1.0)), **out}


SUMMARY_HEADER = ("| run | task, seed | generated in final set | start within 1 cm (median) | hand-object at the start: "
                  "sample vs data, m | sample return, claimed → replayed | replays that succeed | mean: top-k → final, "
                  "claimed / **replayed** | max: top-k → final, claimed / **replayed** | policy |")


def _pct(v) -> str:
    return "—" if v is None else f"{100 * v:.0f}%"


def _with_sample_summary(entry: dict) -> dict:
    """Files written before the summary fields existed (session 29) derive them from their samples."""
    if "start_within_tolerance" in entry:
        return entry
    return {**entry, **summarize_samples(entry.get("samples") or [])}


def summary_row(label: str, entry: dict, *, policy: float | None = None) -> str:
    """One Markdown row (:data:`SUMMARY_HEADER`) of an :func:`open_loop` entry (or the recipe's ``analysis.open_loop``;
    on locomotion, where every trajectory is replayed from its own start and returns are plain, the start and
    success columns are "own start" and "—")."""
    n = entry["num_generated"]
    fmt = lambda v: "—" if v is None else f"{v:.0f}"  # noqa: E731
    cm = lambda v: "—" if v is None else f"{100 * v:.1f} cm"  # noqa: E731
    if "horizon" in entry and entry["horizon"] is None:  # locomotion_open_loop_improvement
        imp, column = entry["improvement"]["plain"], "plain"
        start, hand, success = "own start", "—", "—"
    else:
        entry = _with_sample_summary(entry)
        imp, column = entry["improvement"][f"stop_rule_{int(entry.get('horizon', 500))}"], "stop_rule"
        hand = (f"{entry['start_hand_object_median']:.3f} vs {entry['data_start_hand_object_median']:.3f}"
                if n and "start_hand_object_median" in entry else "—")
        start = f"{_pct(entry.get('start_within_tolerance'))} ({cm(entry.get('start_distance_median'))})" if n else "—"
        success = _pct(entry.get("replay_success_rate")) if n else "—"
    c, r = imp["claimed"], imp["replayed"]
    sample = (f"{fmt(entry.get(f'claimed_{column}_mean_generated'))} → "
              f"{fmt(entry.get(f'replayed_{column}_mean_generated'))}" if n else "—")
    return (f"| {label} | {entry['env']} s{entry['seed']} | {n} | {start} | {hand} | {sample} | {success} | "
            f"{c['true_return_mean_before']:.0f} → {c['true_return_mean_after']:.0f} / "
            f"**{r['true_return_mean_before']:.0f} → {r['true_return_mean_after']:.0f}** | "
            f"{c['true_return_max_before']:.0f} → {c['true_return_max_after']:.0f} / "
            f"**{r['true_return_max_before']:.0f} → {r['true_return_max_after']:.0f}** | "
            f"{'—' if policy is None else f'{policy:.2f}'} |")


def summarize(paths: list[Path]) -> str:
    """The Markdown table of results files: this bench's (``runs``) or table1 cells with ``analysis.open_loop``."""
    rows = [SUMMARY_HEADER, "|" + "---|" * SUMMARY_HEADER.count(" | ") + "---|"]
    for path in paths:
        data = json.loads(Path(path).read_text())
        if "runs" in data:
            for run, entry in data["runs"].items():
                rows.append(summary_row(Path(path).stem, entry))
        else:
            metrics = data.get("metrics", data)
            entry = metrics.get("analysis", {}).get("open_loop")
            if entry is None:
                raise SystemExit(f"{path}: neither this bench's results nor a run with analysis.open_loop")
            entry = {"env": metrics["env"], "seed": metrics["seed"], **entry}
            ev = metrics["eval"]  # Meta-World: success rate; locomotion: D4RL-normalised score
            rows.append(summary_row(Path(path).parent.name, entry,
                                    policy=ev.get("success_rate", ev.get("normalized_score"))))
    return "\n".join(rows)


def describe(run: Path, entry: dict) -> str:
    """The printed lines of one measured run: claimed vs replayed, per return definition."""
    lines = []
    for name, v in entry["improvement"].items():
        c, r = v["claimed"], v["replayed"]
        lines.append(f"{entry['env']} seed {entry['seed']} {name}: mean {c['true_return_mean_before']:.0f} -> "
                     f"{c['true_return_mean_after']:.0f} claimed / {r['true_return_mean_after']:.0f} replayed; max "
                     f"{c['true_return_max_before']:.0f} -> {c['true_return_max_after']:.0f} claimed / "
                     f"{r['true_return_max_after']:.0f} replayed")
    for row in entry.get("top_k_action_noise", []):
        lines.append(f"  top-k actions + N(0, {row['action_noise_std']}): replayed mean {row['return_mean']:.0f}, "
                     f"ended early {100 * row['terminated_early']:.0f}%")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path)
    parser.add_argument("--summarize", nargs="+", type=Path, help="print the Markdown table of these results files")
    parser.add_argument("--horizon", type=int, default=500, help="the stop-rule return's horizon (Meta-World: 500)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "open_loop.json")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-hold", action="store_true",
                        help="stop each replay after the sample's last action (default: the hand then holds still, "
                             "zero actions, until the stop rule or the time limit)")
    parser.add_argument("--action-noise", type=float, nargs="*", default=[0.05, 0.1, 0.2, 0.4],
                        help="locomotion runs: also replay the top-k's own actions with Gaussian noise of these stds "
                             "(how fragile open loop is on the data)")
    args = runs_from_args(parser, summarize)
    if args is None:
        return

    def measure(run: Path) -> dict:
        if env_kind(str(OmegaConf.load(run / "config.yaml").env.name)) == "locomotion":
            return locomotion_open_loop(run, noise=args.action_noise, progress=not args.no_progress)
        return open_loop(run, horizon=args.horizon, progress=not args.no_progress, hold=not args.no_hold)

    measure_runs(args.run_dirs, args.out, {"horizon": args.horizon, "hold": not args.no_hold,
                                           "action_noise": args.action_noise}, measure, describe)


if __name__ == "__main__":
    main()
