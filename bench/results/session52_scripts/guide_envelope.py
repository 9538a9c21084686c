"""Session 52: where do score-guided Meta-World samples put the hand? Samples C top-block conditions of one run
(DDPM 20 steps, guidance 1.2, the run's diffuser, one noise seed) without and with score guidance lambda, and reports,
per setting, the share of valid steps whose hand (obs[0:3]) lies outside the dataset's hand envelope (per axis,
[min - 1 cm, max + 1 cm]) and by how far, the hand's distance to the object (obs[4:7]) against the dataset's smallest,
the mean hand offset from the unguided sample with the same noise (per axis, cm), the claimed stop-rule return, and
the share of samples flow.max_hand_penetration=0 passes (the hand never closer to the object than the dataset's hand
ever is) with the claimed return of those that pass and of those that fail.

usage: python bench/results/session52_scripts/guide_envelope.py RUN_DIR OUT.json [--lambdas 0 0.1 0.3] [--conditions 32]
"""
import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from flow_diagnostics import load_run, sample_true_return  # noqa: E402

from torchrl_ftb.diffusion import load_diffuser  # noqa: E402
from torchrl_ftb.envs import metaworld_closest_approach, metaworld_hand_penetration, true_reward_fn  # noqa: E402
from torchrl_ftb.preference import load_score_model, score_objective  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

p = argparse.ArgumentParser()
p.add_argument("run", type=Path)
p.add_argument("out", type=Path)
p.add_argument("--lambdas", type=float, nargs="+", default=[0.0, 0.1, 0.3])
p.add_argument("--conditions", type=int, default=32)
args = p.parse_args()
torch.set_num_threads(1)
cfg, trajs, returns = load_run(args.run, with_returns=True, horizon=500)
blocks = torch.load(args.run / "checkpoints" / "blocks.pt", weights_only=True)
scores, ids = blocks["scores"], blocks["block_ids"]
diffuser = load_diffuser(args.run / "checkpoints" / "diffuser" / "diffuser_last.pt")
score = score_objective(load_score_model(args.run / "checkpoints" / "score_model.pt"), float(scores.min()),
                        float(scores.max()))
reward_fn = true_reward_fn(str(cfg.env.name), with_success=True)
top = (ids == ids.max()).nonzero().squeeze(-1)[: args.conditions]
real = trajs["observation"][trajs["mask"]]
lo, hi = real[:, 0:3].amin(0) - 0.01, real[:, 0:3].amax(0) + 0.01
reach_data = float((real[:, 0:3] - real[:, 4:7]).norm(dim=-1).min())
closest = float(metaworld_closest_approach(trajs).min())
rows, plain = [], None
for lam in args.lambdas:
    s = diffuser.generate(trajs[top], sampler="ddpm", steps=20, guidance=1.2, generator=torch.Generator().manual_seed(0),
                          guide=score if lam > 0 else None, guide_scale=lam)
    if plain is None:
        plain = s
    both = s["mask"] & plain["mask"]
    hand = s["observation"][s["mask"]][:, 0:3]
    beyond = torch.maximum(lo - hand, hand - hi).clamp_min(0)
    outside = beyond.amax(-1) > 0
    offset = (s["observation"][both][:, 0:3] - plain["observation"][both][:, 0:3]) * 100
    true = sample_true_return(s, reward_fn, horizon=500, streak=25).double()
    row = {"lambda": lam, "true_mean": float(true.mean()), "true_max": float(true.max()),
           "steps_outside_hand_envelope": float(outside.double().mean()),
           "outside_by_cm_median": float(beyond.amax(-1)[outside].median() * 100) if bool(outside.any()) else 0.0,
           "outside_axis_share": [float((beyond[:, i] > 0).double().mean()) for i in range(3)],
           "hand_object_distance_min_cm": float((s["observation"][s["mask"]][:, 0:3]
                                                 - s["observation"][s["mask"]][:, 4:7]).norm(dim=-1).min() * 100),
           "offset_from_unguided_cm_mean_xyz": [float(v) for v in offset.mean(0)],
           "offset_from_unguided_cm_abs_xyz": [float(v) for v in offset.abs().mean(0)]}
    ok = metaworld_hand_penetration(s, closest) <= 0
    row.update(pass_penetration_0=float(ok.double().mean()),
               true_mean_passing=float(true[ok].mean()) if bool(ok.any()) else None,
               true_mean_failing=float(true[~ok].mean()) if bool((~ok).any()) else None,
               true_max_passing=float(true[ok].max()) if bool(ok.any()) else None)
    print({k: (round(v, 3) if isinstance(v, float) else [round(x, 3) for x in v] if isinstance(v, list) else v)
           for k, v in row.items()}, flush=True)
    rows.append(row)
write_json(args.out, {**run_record(config={"run_dir": str(args.run), "conditions": len(top), "sampler": "ddpm",
                                           "steps": 20, "guidance": 1.2, "seed": 0, "lambdas": args.lambdas}),
                      "data": {"hand_low_cm": [float(v) * 100 for v in lo], "hand_high_cm": [float(v) * 100 for v in hi],
                               "hand_object_distance_min_cm": reach_data * 100, "closest_approach_cm": closest * 100,
                               "true_max_data": float(returns.max())},
                      "rows": rows})
