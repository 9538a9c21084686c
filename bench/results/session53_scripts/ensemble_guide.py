"""Session 53: is score guidance limited by s_psi's own blind spots? Score guidance lifts s_psi far more than the true
return, and on SDEdit edits (a sample ~0.1 from its real condition) it lifts s_psi while the true return falls
(sdedit_sg_sweep.sh): the guide finds directions s_psi rewards and the task does not. This script trains an ensemble
of M score models on the run's own labels (the run's score-model settings, members initialised apart; kept in
WORK/score_ensemble.pt) and guides the top block's samples with (a) the run's s_psi, (b) the ensemble's mean,
(c) its pessimistic bound mean - kappa * std over members, each on the dataset's [0, 1] scale (the flow's), at each
lambda, fresh samples (strength 1) and SDEdit edits (strength 0.3). DDPM 20 steps, guidance 1.2, one noise seed.
Reported per setting: the samples' claimed stop-rule return (mean, max; the conditions' beside them), the share above
their own condition, the run's s_psi and the ensemble mean (normalised), and the ensemble's Spearman with the true
return on the dataset beside the run's s_psi's.

usage: python bench/results/session53_scripts/ensemble_guide.py RUN_DIR WORK_DIR OUT.json [--members 5]
    [--kappa 1] [--lambdas 0 0.3 1] [--strengths 1 0.3] [--conditions 32]
"""
import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from flow_diagnostics import load_run, sample_true_return  # noqa: E402

from torchrl_ftb.data.labels import load_labels  # noqa: E402
from torchrl_ftb.diffusion import load_diffuser  # noqa: E402
from torchrl_ftb.envs import true_reward_fn  # noqa: E402
from torchrl_ftb.preference import (load_score_model, normalized_scores, save_score_model,  # noqa: E402
                                    score_objective, score_trajectories)
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402
from torchrl_ftb.testing import load_script  # noqa: E402


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    ra, rb = a.argsort().argsort().double(), b.argsort().argsort().double()
    return float(torch.corrcoef(torch.stack([ra, rb]))[0, 1])


def lcb_objective(model, kappa: float, s_min: float, s_max: float):
    """mean - kappa * std over the members' scores, on the mean's dataset span."""
    def objective(trajs):
        m = model.score(trajs, members=True)  # [M, N]
        return normalized_scores(m.mean(0) - kappa * m.std(0), s_min, s_max)
    return objective


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("run", type=Path)
    p.add_argument("work", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--members", type=int, default=5)
    p.add_argument("--kappa", type=float, default=1.0)
    p.add_argument("--lambdas", type=float, nargs="+", default=[0.0, 0.3, 1.0])
    p.add_argument("--strengths", type=float, nargs="+", default=[1.0, 0.3])
    p.add_argument("--conditions", type=int, default=32)
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg, trajs, returns = load_run(args.run, with_returns=True, horizon=500)
    single = load_score_model(args.run / "checkpoints" / "score_model.pt")
    args.work.mkdir(parents=True, exist_ok=True)
    ens_path = args.work / "score_ensemble.pt"
    if ens_path.exists():
        ens = load_score_model(ens_path)
    else:
        recipe = load_script(ROOT / "recipes" / "ftb_offline.py", "recipe_ensemble_guide")
        labels, _ = load_labels(args.run / "checkpoints" / "labels")
        ens_cfg = OmegaConf.merge(cfg, {"score_model": {"num_members": args.members}, "progress": False})
        ens = recipe.make_score_model(ens_cfg, trajs["observation"].shape[-1], trajs["action"].shape[-1], "cpu")
        recipe.fit_score_model(ens_cfg, ens, trajs, labels, "cpu")
        save_score_model(ens, ens_path)
    with torch.no_grad():
        s1, se = score_trajectories(single, trajs), score_trajectories(ens, trajs)
        members = torch.cat([ens.score(trajs[i:i + 64], members=True) for i in range(0, trajs.batch_size[0], 64)], -1)
    lcb_data = members.mean(0) - args.kappa * members.std(0)
    objectives = {"single": score_objective(single, float(s1.min()), float(s1.max())),
                  "ensemble_mean": score_objective(ens, float(se.min()), float(se.max())),
                  f"ensemble_lcb{args.kappa:g}": lcb_objective(ens, args.kappa, float(lcb_data.min()),
                                                                float(lcb_data.max()))}
    data = {"spearman_single": spearman(s1, returns), "spearman_ensemble_mean": spearman(se, returns),
            "spearman_ensemble_lcb": spearman(lcb_data, returns), "true_max_data": float(returns.max())}
    print(data, flush=True)
    blocks = torch.load(args.run / "checkpoints" / "blocks.pt", weights_only=True)
    ids = blocks["block_ids"]
    top = (ids == ids.max()).nonzero().squeeze(-1)[: args.conditions]
    cond_true = returns[top]
    diffuser = load_diffuser(args.run / "checkpoints" / "diffuser" / "diffuser_last.pt")
    reward_fn = true_reward_fn(str(cfg.env.name), with_success=True)
    rows = []
    for strength in args.strengths:
        for name, objective in objectives.items():
            for lam in args.lambdas:
                if lam == 0 and name != "single":
                    continue  # lambda 0: no guide, one row per strength
                s = diffuser.generate(trajs[top], sampler="ddpm", steps=20, guidance=1.2,
                                      generator=torch.Generator().manual_seed(0),
                                      init=trajs[top] if strength < 1 else None, strength=strength,
                                      guide=objective if lam > 0 else None, guide_scale=lam)
                true = sample_true_return(s, reward_fn, horizon=500, streak=25).double()
                with torch.no_grad():
                    row = {"strength": strength, "objective": name if lam > 0 else "none", "lambda": lam,
                           "true_mean": float(true.mean()), "true_max": float(true.max()),
                           "conditions_true_mean": float(cond_true.mean()), "conditions_true_max": float(cond_true.max()),
                           "above_own_condition": float((true > cond_true).double().mean()),
                           "single_score_norm": float(objectives["single"](s).mean()),
                           "ensemble_score_norm": float(objectives["ensemble_mean"](s).mean())}
                print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
                rows.append(row)
                write_json(args.out, {**run_record(config={"run_dir": str(args.run), "members": args.members,
                                                           "kappa": args.kappa, "conditions": len(top),
                                                           "sampler": "ddpm", "steps": 20, "guidance": 1.2, "seed": 0,
                                                           "lambdas": args.lambdas, "strengths": args.strengths}),
                                      "data": data, "rows": rows})


if __name__ == "__main__":
    main()
