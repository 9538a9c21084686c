"""Session 57: does the guide rate a guided run's generated paths above the top-k while the simulator does not?

For each guided run (``checkpoints/guide_score_model.pt``, the ensemble the flow climbed) and its readers reading
(session 49's ``readers.sh``: each generated path executed 4 times), reports, on the flow's scale (the guide's
pessimistic score ``mean - kappa * std`` normalised by its span on the dataset, as ``recipes/ftb_offline.py``'s
``flow_guide`` does; s_psi by its own dataset span):

- each score's Spearman with the true return (stop-rule, ``--horizon``) on the dataset;
- the top-k's and the generated paths' mean and max score, and the generated paths' executed return (mean of the
  readings) and claimed return (read off their states);
- the share of generated paths the guide rates above the top-k's best-rated path, and how many of those execute
  above the top-k's best true return in every reading on path;
- each score's Spearman with the executed return over the generated paths (does the guide still rank what it made?).

The readers' samples are the final set's generated entries in order (``torchrl_ftb.analysis.tracking``); the script
checks their lengths against the final set's masks.

usage: python bench/results/session57_scripts/guide_reading.py OUT.json RUN_DIR=READERS.json [...] [--horizon 500]
       python bench/results/session57_scripts/guide_reading.py --table OUT.json   (Markdown rows of a written file)
"""
import argparse
import json
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from flow_diagnostics import load_run, spearman  # noqa: E402
from flow_generated import load_flow_sets  # noqa: E402

from torchrl_ftb.preference import load_score_model  # noqa: E402
from torchrl_ftb.preference.score import normalized_scores, pessimistic_scores  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def scaled(model, trajs, data, *, kappa: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(scores of trajs, scores of data)`` normalised by the data's span (the flow's [0, 1] scale)."""
    on_data = pessimistic_scores(model, data, kappa=kappa).double()
    lo, hi = float(on_data.min()), float(on_data.max())
    return (normalized_scores(pessimistic_scores(model, trajs, kappa=kappa).double(), lo, hi),
            normalized_scores(on_data, lo, hi))


def read_run(run: Path, readers: Path, *, horizon: int) -> dict:
    """One run's entry (see the module docstring)."""
    cfg = OmegaConf.load(run / "config.yaml")
    _, data, returns = load_run(run, with_returns=True, horizon=horizon)
    ckpt, final, original, generated = load_flow_sets(run)
    reading = next(iter(json.loads(readers.read_text())["runs"].values()))
    samples = reading["samples"]
    gen = final[generated]
    lengths = gen["mask"].sum(-1).tolist()
    if len(samples) != len(lengths) or any(int(s["length"]) != int(n) for s, n in zip(samples, lengths)):
        raise ValueError(f"{readers}: its {len(samples)} samples do not match {run}'s generated paths "
                         f"({len(lengths)}) in order and length")
    executed = torch.tensor([s["tracked_stop_rule"] for s in samples], dtype=torch.float64)
    lowest = torch.tensor([min(s["tracked_stop_rule_per_reader"]) for s in samples], dtype=torch.float64)
    bound = float(reading["fidelity"]["tracker_alone_hand_deviation_max"])
    on_path = torch.tensor([max(s["hand_deviation_per_reader"]) <= bound for s in samples])
    claimed = torch.tensor([s["claimed_stop_rule"] for s in samples], dtype=torch.float64)
    rows = torch.as_tensor(ckpt["original_indices"])
    best_true = float(reading["tracked_on_path"]["true_return_max_before"])  # the top-k's best, executed (sg_rows.py's)
    kappa = float(cfg.diffuser.get("score_guidance_kappa", 0.0))
    entry = {"run": str(run), "readers": str(readers), "env": str(cfg.env.name), "seed": int(cfg.seed),
             "score_guidance": float(cfg.diffuser.get("score_guidance", 0.0)), "kappa": kappa,
             "num_generated": len(samples), "on_path": int(on_path.sum()),
             "top_k_executed_max": best_true,
             "top_k_executed_mean": float(reading["tracked_on_path"]["true_return_mean_before"]),
             "top_k_true_return_mean": float(returns[rows].mean()),
             "generated_executed_mean": float(executed.mean()), "generated_claimed_mean": float(claimed.mean())}
    models = {"guide": (load_score_model(run / "checkpoints" / "guide_score_model.pt"), kappa),
              "s_psi": (load_score_model(run / "checkpoints" / "score_model.pt"), 0.0)}
    for name, (model, k) in models.items():
        with torch.no_grad():
            on_gen, on_data = scaled(model, gen, data, kappa=k)
        on_top = on_data[rows]
        above = on_gen > on_top.max()
        entry[name] = {
            "spearman_true_return_dataset": spearman(on_data, returns),
            "top_k_mean": float(on_top.mean()), "top_k_max": float(on_top.max()),
            "generated_mean": float(on_gen.mean()), "generated_max": float(on_gen.max()),
            "generated_rated_above_top_k_mean": int((on_gen > on_top.mean()).sum()),
            "generated_rated_above_top_k_best": int(above.sum()),
            "of_those_on_path_above_true_best_every_reading": int((above & on_path & (lowest > best_true)).sum()),
            "of_those_executed_mean": float(executed[above].mean()) if bool(above.any()) else None,
            "spearman_executed_generated": spearman(on_gen, executed),
            "spearman_claimed_generated": spearman(on_gen, claimed),
        }
    return entry


TABLE_HEADER = ("| run | Spearman with the true return on the dataset, guide / s_ψ | guide's rating, top-k mean (max) → "
                "generated mean (max) | generated the guide rates above the top-k's best | s_ψ's rating, top-k mean → "
                "generated mean | executed, top-k mean → generated mean (on path of generated) | Spearman with the "
                "executed return over the generated paths, guide / s_ψ |\n|---|---|---|---|---|---|---|")


def table(path: Path) -> str:
    """Markdown rows of a written file, one per run."""
    lines = [TABLE_HEADER]
    for e in json.loads(path.read_text())["runs"]:
        g, s = e["guide"], e["s_psi"]
        lines.append(
            f"| {e['env'].removesuffix('-v3')} s{e['seed']}, λ {e['score_guidance']:g} "
            f"| {g['spearman_true_return_dataset']:.2f} / {s['spearman_true_return_dataset']:.2f} "
            f"| {g['top_k_mean']:.2f} ({g['top_k_max']:.2f}) → {g['generated_mean']:.2f} ({g['generated_max']:.2f}) "
            f"| {g['generated_rated_above_top_k_best']} / {e['num_generated']} "
            f"| {s['top_k_mean']:.2f} → {s['generated_mean']:.2f} "
            f"| {e['top_k_executed_mean']:,.0f} → {e['generated_executed_mean']:,.0f} ({e['on_path']} / {e['num_generated']}) "
            f"| {g['spearman_executed_generated']:+.2f} / {s['spearman_executed_generated']:+.2f} |")
    return "\n".join(lines)


def main() -> None:
    if sys.argv[1:2] == ["--table"]:
        print(table(Path(sys.argv[2])))
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("pairs", nargs="+", help="RUN_DIR=READERS.json")
    p.add_argument("--horizon", type=int, default=500)
    args = p.parse_args()
    entries = []
    for pair in args.pairs:
        run, readers = pair.split("=", 1)
        entries.append(read_run(Path(run), Path(readers), horizon=args.horizon))
        e = entries[-1]
        print(f"{e['env']} s{e['seed']} λ {e['score_guidance']}: " + "; ".join(
            f"{n}: ρ data {e[n]['spearman_true_return_dataset']:.2f}, top-k {e[n]['top_k_mean']:.2f}/{e[n]['top_k_max']:.2f}"
            f" gen {e[n]['generated_mean']:.2f}/{e[n]['generated_max']:.2f}, above {e[n]['generated_rated_above_top_k_best']}"
            f" (rise {e[n]['of_those_on_path_above_true_best_every_reading']}), ρ executed "
            f"{e[n]['spearman_executed_generated']:.2f}" for n in ("guide", "s_psi")))
    write_json(args.out, {**run_record(config={k: str(v) for k, v in vars(args).items()}), "runs": entries})
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
