"""What a Table-2 supplement's trajectories are worth executed: the dataset's top-k against the supplement,
claimed, open loop and tracked, on locomotion.

``recipes/baselines.py augmentation.kind=ftb|synthetic`` reports a supplement's return as its transitions claim it
(the simulator's reward of each generated ``(s, a)``) and replayed open loop. This bench adds the closed-loop
reading the FTB recipe has (``analysis.tracked``): every trajectory of the dataset's top-k by return (what the
augmentation flow starts from) and of the supplement is tracked from its own first state by
:func:`torchrl_ftb.envs.track_locomotion_paths` (:func:`torchrl_ftb.analysis.locomotion_tracked_improvement`), and
replayed open loop (:func:`torchrl_ftb.analysis.locomotion_open_loop_improvement`), so both sides are read alike.
It reads supplements already built (``<cache_dir>/<kind>-<hash>/supplement.pt``); it trains nothing.

Usage::

    python bench/supplement_readings.py --dataset hopper-medium-replay \\
        --supplements s0=RUNS/supplements/hopper-medium-replay/seed0/ftb-<hash>/supplement.pt ... \\
        --out bench/results/supplement_readings.json
    python bench/supplement_readings.py --plot readings.png --from-json A.json B.json   # plot finished readings
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.analysis import (  # noqa: E402
    TrackedTopK,
    locomotion_open_loop_improvement,
    locomotion_tracked_improvement,
    save_figure,
    track_top_k,
)
from torchrl_ftb.augmentation import load_supplement  # noqa: E402
from torchrl_ftb.data import true_return  # noqa: E402
from torchrl_ftb.datasets import make_dataset  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def top_trajectories(data, top_k: int):
    """The top-``top_k`` of ``data`` by return: what the augmentation flow starts from."""
    return data[true_return(data).argsort(descending=True)[:top_k]]


def track_top(dataset: str, top, *, candidates: int, seed: int) -> TrackedTopK:
    """The top-k tracked once, for every supplement's reading (``original_tracked`` of
    :func:`~torchrl_ftb.analysis.locomotion_tracked_improvement`, which checks the options match)."""
    return track_top_k(dataset.split("-", 1)[0], top, candidates=candidates, seed=seed)


def readings(dataset: str, top, supplement_path: str | Path, *, candidates: int, seed: int,
             top_tracked: TrackedTopK | None = None) -> dict:
    """The top-k trajectories ``top`` of the ``dataset`` -> the supplement, claimed / open loop / tracked (module
    docstring); ``top_tracked``: :func:`track_top` of ``top`` with the same options (default: tracked here)."""
    env = dataset.split("-", 1)[0]
    supplement, info = load_supplement(supplement_path)
    if supplement.batch_size[0] == 0:
        raise ValueError(f"{supplement_path}: the supplement holds no trajectories")
    if supplement.batch_size[1] != top.batch_size[1]:
        raise ValueError(f"{supplement_path}: horizon {supplement.batch_size[1]} != the dataset's {top.batch_size[1]}")
    generated = torch.ones(supplement.batch_size[0], dtype=torch.bool)
    open_loop = locomotion_open_loop_improvement(supplement, top, generated, env_name=env)
    tracked = locomotion_tracked_improvement(supplement, top, generated, env_name=env, candidates=candidates, seed=seed,
                                             original_tracked=top_tracked)
    return {"dataset": dataset, "supplement": str(supplement_path), "kind": info.get("kind"),
            "diffuser": info.get("diffuser"), "num_trajectories": int(supplement.batch_size[0]),
            "top_k": int(top.batch_size[0]),
            "claimed": tracked["claimed"], "open_loop": open_loop["improvement"]["plain"]["replayed"],
            "tracked": tracked["tracked"], "tracked_fidelity": tracked["fidelity"],
            "tracked_generated": tracked["generated"],
            "open_loop_terminated_rate": open_loop["replay_terminated_rate"]}


def plot_readings(rows: dict[str, dict], path: str | Path) -> Path:
    """Grouped bars: each supplement's mean return claimed / open loop / tracked, the top-k's mean and the
    data's best as lines (the top-k reads the same in all three)."""
    import matplotlib.pyplot as plt

    labels = list(rows)
    fig, ax = plt.subplots(figsize=(1.2 * len(labels) + 2, 3.5))
    for j, (key, name) in enumerate((("claimed", "claimed by its transitions"), ("open_loop", "open loop"),
                                     ("tracked", "tracked (closed loop)"))):
        ax.bar([i + 0.27 * (j - 1) for i in range(len(labels))],
               [rows[k][key]["true_return_mean_after"] for k in labels], width=0.27, label=name)
    first = rows[labels[0]]["tracked"]
    ax.axhline(first["true_return_mean_before"], color="k", ls="--", lw=1, label="top-k mean")
    ax.axhline(first["true_return_max_before"], color="k", ls=":", lw=1, label="top-k max (data's best)")
    ax.set_xticks(range(len(labels)), labels)
    ax.set_ylabel("return (mean over the supplement)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return save_figure(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="hopper-medium-replay", help="<env>-<kind> of the supplements' data")
    parser.add_argument("--supplements", nargs="+", metavar="LABEL=PATH")
    parser.add_argument("--top-k", type=int, default=100, help="the augmentation flow's top-k (App. B.5: 100)")
    parser.add_argument("--candidates", type=int, default=64, help="the tracker's actions tried per step")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="the results JSON")
    parser.add_argument("--plot", type=Path, help="a PNG of the readings (with --from-json: of those files')")
    parser.add_argument("--from-json", type=Path, nargs="+", help="plot these finished readings; run nothing")
    args = parser.parse_args()
    if args.from_json:
        if args.plot is None:
            parser.error("--from-json needs --plot")
        rows = {k: v for f in args.from_json for k, v in json.loads(f.read_text())["results"].items()}
        print(plot_readings(rows, args.plot))
        return
    if not args.supplements or args.out is None:
        parser.error("--supplements and --out are needed to read supplements")
    env, kind = args.dataset.split("-", 1)
    data, _ = make_dataset(env, kind=kind, progress=False)
    items = [item.partition("=") for item in args.supplements]
    for label, sep, path in items:
        if not sep:
            parser.error(f"--supplements: {label + sep + path!r} is not LABEL=PATH")
    top = top_trajectories(data, args.top_k)
    top_tracked = track_top(args.dataset, top, candidates=args.candidates, seed=args.seed)
    rows = {}
    for label, _, path in items:
        rows[label] = readings(args.dataset, top, path, candidates=args.candidates, seed=args.seed,
                               top_tracked=top_tracked)
        r = rows[label]
        print(f"{label}: mean top-k -> supplement: claimed {r['claimed']['true_return_mean_before']:.0f} -> "
              f"{r['claimed']['true_return_mean_after']:.0f}, open loop {r['open_loop']['true_return_mean_before']:.0f}"
              f" -> {r['open_loop']['true_return_mean_after']:.0f}, tracked {r['tracked']['true_return_mean_before']:.0f}"
              f" -> {r['tracked']['true_return_mean_after']:.0f}", flush=True)
    write_json(args.out, {**run_record(config={k: str(v) for k, v in vars(args).items()}), "results": rows})
    if args.plot is not None:
        plot_readings(rows, args.plot)


if __name__ == "__main__":
    main()
