"""Does the summed score s_psi favour long trajectories? Retrain a run's s_psi with a discount. (issues #3, #5)

``s_psi(tau) = sum_h gamma^h r_psi(s_h, a_h)`` (paper Eq. 4 with gamma = 1, the recipes' default).
On Meta-World a success ends the episode (mean 136-304 steps by task) while a failure runs all 500, so
wherever r_psi > 0 a failure collects more score just by lasting longer; the top of the ranking
is where that shows. For each given FTB run (``recipes/ftb_offline.py`` run directory) this
retrains the score model exactly as the run's ``score_model`` stage did (its config, labels and
seed; ``score_model.gamma`` replaced by each ``--gammas`` value) and reports, over the run's
dataset: Spearman of the score with true return, success and length, the share of successes among
the top ``k`` for several ``k`` (:func:`torchrl_ftb.preference.top_k_mean`), and the mean length
of the top 25. gamma = 1 reproduces the run's own scores (checked against its ``blocks.pt``).
JSON with command, config, commit and machine. Not a test.

    python bench/score_length_bias.py --run-dirs outputs/table1_v2_active/button-press-v3/success/ftb/seed2 --gammas 1.0 0.99
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.data import load_labels, trajectory_lengths  # noqa: E402
from torchrl_ftb.data.labels import SuccessTeacher, true_return  # noqa: E402
from torchrl_ftb.datasets import dataset_kwargs, make_dataset  # noqa: E402
from torchrl_ftb.preference import correlations, score_trajectories, top_k_mean  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402
from torchrl_ftb.testing import load_script  # noqa: E402

RECIPE = load_script(ROOT / "recipes" / "ftb_offline.py", "ftb_offline_recipe")

KS = (25, 50, 100, 150)


def retrain_scores(cfg, trajs, labels, *, gamma: float) -> torch.Tensor:
    """Scores ``[N]`` of the run's score model retrained by the recipe's own code with ``gamma``."""
    cfg = OmegaConf.merge(cfg, {"score_model": {"gamma": gamma}, "progress": False})
    model = RECIPE.make_score_model(cfg, trajs["observation"].shape[-1], trajs["action"].shape[-1], "cpu")
    RECIPE.fit_score_model(cfg, model, trajs, labels, "cpu")
    return score_trajectories(model, trajs.select("observation", "action", "mask")).cpu()


def ranking_report(scores: torch.Tensor, returns: torch.Tensor, success: torch.Tensor, lengths: torch.Tensor) -> dict:
    """Correlations and top-k success shares of one score vector."""
    return {
        "spearman_return": correlations(scores, returns)["spearman"],
        "spearman_success": correlations(scores, success)["spearman"],
        "spearman_length": correlations(scores, lengths)["spearman"],
        "top_k_success": {str(k): top_k_mean(scores, success, k) for k in KS},
        "top25_length_mean": top_k_mean(scores, lengths, 25),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--gammas", nargs="+", type=float, default=[1.0, 0.99])
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "score_length_bias.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    record = {**run_record(config={"run_dirs": [str(r) for r in args.run_dirs], "gammas": args.gammas}), "runs": {}}
    for run in args.run_dirs:
        cfg = OmegaConf.load(run / "config.yaml")
        name = str(cfg.env.name)
        trajs, _ = make_dataset(name, **dataset_kwargs(name, cfg.dataset, progress=False,
                                                       max_episode_steps=int(cfg.env.max_episode_steps)))
        labels, _ = load_labels(run / "checkpoints" / "labels")
        returns = true_return(trajs, discount=float(cfg.labels.discount))
        success, lengths = SuccessTeacher().succeeded(trajs).float(), trajectory_lengths(trajs).float()
        own = torch.load(run / "checkpoints" / "blocks.pt", weights_only=True)["scores"]
        rep = {"env": name, "seed": int(cfg.seed), "teacher": str(cfg.labels.teacher),
               "labels": str(OmegaConf.select(cfg, "labels.query.strategy", default="random")),
               "run_gamma": float(cfg.score_model.gamma), "dataset_success": float(success.mean()),
               "run": ranking_report(own, returns, success, lengths), "gammas": {}}
        for gamma in args.gammas:
            scores = retrain_scores(cfg, trajs, labels, gamma=gamma)
            res = ranking_report(scores, returns, success, lengths)
            if gamma == float(cfg.score_model.gamma):
                res["max_abs_diff_to_run_scores"] = float((scores - own).abs().max())
            rep["gammas"][str(gamma)] = res
            tk = " ".join(f"{k}:{v:.2f}" for k, v in res["top_k_success"].items())
            print(f"{name} {rep['teacher']} {rep['labels']} seed {rep['seed']} gamma {gamma}: spearman return "
                  f"{res['spearman_return']:.3f} success {res['spearman_success']:.3f} length "
                  f"{res['spearman_length']:.3f} | top-k success {tk} | top-25 length {res['top25_length_mean']:.0f}",
                  flush=True)
        record["runs"][str(run)] = rep
        write_json(args.out, record)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
