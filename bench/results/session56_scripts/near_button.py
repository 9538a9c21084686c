"""Session 56: what the ensemble-guided button-press sets teach at the button. Meta-World's scripted button-press
expert aligns the hand in x/z with the button, then pushes it in by moving +y (metaworld.policies
SawyerButtonPressV3Policy); so the sign of a path's y action while the hand is near the button (within RADIUS m of the
button's observed position, obs[0:3] vs obs[4:7]) says whether it pushes (+) or backs off (-). Per run (the final
set's split by a readers reading, session 53's bc_subsets.load_split):

- for the original top-k, the on-path and the off-path generated paths: paths, mean length, mean steps near the
  button, the mean action near the button, and the share of paths whose mean y action near it is positive;
- the guide's (``checkpoints/guide_score_model.pt``, its kappa) and s_psi's (``score_model.pt``) gradient at the
  top-k's near-button steps, through their normalised objective (torchrl_ftb.preference.score_objective): its mean
  and share > 0 for the y action and for the hand's y position.

usage: python bench/results/session56_scripts/near_button.py OUT.json [--radius 0.12] [--kappa 1] RUN=READERS.json ...
"""
import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session53_scripts"))
from bc_subsets import load_split  # noqa: E402

from torchrl_ftb.preference.score import load_score_model, pessimistic_scores, score_objective  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

KEYS = ("observation", "action", "mask")


def near_button(td, radius: float) -> torch.Tensor:
    o, m = td["observation"], td["mask"].bool()
    return ((o[..., 0:3] - o[..., 4:7]).norm(dim=-1) < radius) & m


def actions_near(td, radius: float) -> dict:
    a, m, near = td["action"].double(), td["mask"].bool(), near_button(td, radius)
    per_path_y = (a[..., 1] * near).sum(-1) / near.sum(-1).clamp_min(1)
    reach = near.any(-1)
    return {"paths": int(td.batch_size[0]), "length_mean": float(m.sum(-1).double().mean()),
            "near_steps_per_path": float(near.sum(-1).double().mean()),
            "action_near_mean": [float(v) for v in a[near].mean(0)] if near.any() else None,
            "paths_pushing_share": float((per_path_y[reach] > 0).double().mean()) if reach.any() else None}


def gradient_near(model, td, radius: float, kappa: float) -> dict:
    span = pessimistic_scores(model, td, kappa=kappa)
    objective = score_objective(model, float(span.min()), float(span.max()), kappa=kappa)
    x = td.clone()
    x.set("action", td["action"].clone().requires_grad_(True))
    x.set("observation", td["observation"].clone().requires_grad_(True))
    objective(x).sum().backward()
    near = near_button(td, radius)
    ga, go = x["action"].grad[near], x["observation"].grad[near]
    return {"kappa": kappa, "near_steps": int(near.sum()),
            "d_action_y_mean": float(ga[:, 1].mean()), "d_action_y_positive_share": float((ga[:, 1] > 0).double().mean()),
            "d_hand_y_mean": float(go[:, 1].mean()), "d_hand_y_positive_share": float((go[:, 1] > 0).double().mean())}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("out", type=Path)
    p.add_argument("pairs", nargs="+", help="RUN_DIR=READERS.json")
    p.add_argument("--radius", type=float, default=0.12)
    p.add_argument("--kappa", type=float, default=1.0, help="the guide's kappa (the runs' diffuser.score_guidance_kappa)")
    args = p.parse_args()
    torch.set_num_threads(1)
    record = {**run_record(config={"pairs": args.pairs, "radius": args.radius, "kappa": args.kappa}), "runs": {}}
    for pair in args.pairs:
        run, readers = (Path(x) for x in pair.split("=", 1))
        cfg, final, original, generated, off = load_split(run, readers)
        top, gen = original.select(*KEYS), final[generated].select(*KEYS)
        entry = {"seed": int(cfg.seed), "topk": actions_near(top, args.radius),
                 "on_path": actions_near(gen[~off], args.radius), "off_path": actions_near(gen[off], args.radius)}
        for name, kappa in (("guide_score_model.pt", args.kappa), ("score_model.pt", 0.0)):
            if (run / "checkpoints" / name).is_file():
                entry[f"gradient_{name[:-3]}"] = gradient_near(load_score_model(run / "checkpoints" / name), top,
                                                               args.radius, kappa)
        record["runs"][str(run)] = entry
        print(run.name, entry, flush=True)
    write_json(args.out, record)


if __name__ == "__main__":
    main()
