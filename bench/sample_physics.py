"""Are a trained diffuser's fresh samples physically plausible? Meta-World proxies of one flow step.

For each FTB run directory (``recipes/ftb_offline.py``), takes the run's top-k trajectories by
s_psi (its ``blocks.pt`` scores), draws one sample for each of the first ``--conditions`` of them
with the run's own diffuser and sampler settings (what the flow's first step proposes, before
any filter), and reports the three Meta-World dynamics proxies (``torchrl_ftb.envs``: stacked
previous frame, one-step hand model, object motion out of the hand's reach), the hand model and
reach fitted on that top-k, next to the top-k's own values, plus the mean generated and
condition lengths. It tells whether a change to the diffuser (e.g. ``prediction_type``) makes
samples that the flow's physics checks (``flow.max_hand_model_error`` ...) would pass.

Usage::

    python bench/sample_physics.py --run-dirs RUN [RUN ...] --out bench/results/sample_physics.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_diagnostics import load_run, sampling_settings  # noqa: E402
from flow_generated import physics_reference  # noqa: E402

from torchrl_ftb.diffusion import load_diffuser  # noqa: E402
from torchrl_ftb.envs import env_kind, metaworld_physics_errors  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def sample_physics(run: Path, *, conditions: int, top_k: int | None, seed: int,
                   contact_quantile: float = 0.99) -> dict:
    """Proxies of ``conditions`` first-step samples of ``run``'s diffuser (see module docstring)."""
    name = str(OmegaConf.load(run / "config.yaml").env.name)
    if env_kind(name) != "metaworld":  # the proxies read Meta-World's observation layout
        raise ValueError(f"{run}: sample_physics needs a Meta-World run, got env {name!r}")
    cfg, trajs = load_run(run)
    blocks = torch.load(run / "checkpoints" / "blocks.pt", weights_only=True)
    k = int(top_k or cfg.flow.top_k)
    top = trajs[blocks["scores"].argsort(descending=True)[:k]]
    ref = physics_reference(top, contact_quantile=contact_quantile)  # the calibration flow_generated uses
    hand_w, reach = ref["hand_weights"], ref["contact_reach_m"]
    diffuser = load_diffuser(run / "checkpoints" / "diffuser" / "diffuser_last.pt")
    sampler, steps, guidance = sampling_settings(cfg)
    cond = top[:conditions]
    samples = diffuser.generate(cond, sampler=sampler, steps=steps, guidance=guidance,
                                generator=torch.Generator().manual_seed(seed))
    real = metaworld_physics_errors(top, hand_weights=hand_w, reach=reach)
    gen = metaworld_physics_errors(samples, hand_weights=hand_w, reach=reach)
    return {"env": name, "seed": int(cfg.seed), "top_k": k, "conditions": int(conditions),
            "prediction_type": diffuser.process.prediction_type, "diffuser_steps": int(cfg.diffuser.steps or 0),
            "sampler": sampler, "sample_steps": steps, "guidance": guidance,
            "length_mean": {"samples": float(samples["mask"].sum(-1).float().mean()),
                            "conditions": float(cond["mask"].sum(-1).float().mean())},
            "proxies_m": {proxy: {"samples_median": float(v.median()), "samples_mean": float(v.mean()),
                                  "top_k_median": float(real[proxy].median()), "top_k_max": float(real[proxy].max())}
                          for proxy, v in gen.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--conditions", type=int, default=40, help="samples per run (the top conditions)")
    parser.add_argument("--top-k", type=int, default=None, help="default: the run's flow.top_k")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "sample_physics.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    for run in args.run_dirs:
        if not (run / "checkpoints" / "diffuser" / "diffuser_last.pt").exists():
            parser.error(f"{run}: no trained diffuser (checkpoints/diffuser/diffuser_last.pt)")
    record = {**run_record(config=vars(args)), "runs": {}}
    for run in args.run_dirs:
        r = record["runs"][str(run)] = sample_physics(run, conditions=args.conditions, top_k=args.top_k,
                                                      seed=args.seed)
        p = r["proxies_m"]
        print(f"{r['env']} seed {r['seed']} ({r['prediction_type']}): length {r['length_mean']['conditions']:.0f} -> "
              f"{r['length_mean']['samples']:.0f}; " + "; ".join(
                  f"{n} median {v['samples_median'] * 1000:.1f} mm (top-k max {v['top_k_max'] * 1000:.1f})"
                  for n, v in p.items()), flush=True)
        write_json(args.out, record)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
