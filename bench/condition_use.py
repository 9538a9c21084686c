"""How much does a trained diffuser use its condition, at each noise level?

For a diffuser checkpoint (a recipe run's, or a ``bench/diffuser_conditioning.py`` work dir's) and the
run's trajectories, this bench noises ``--num`` trajectories to fixed timesteps ``t`` and reads the
denoiser's error against its training target three ways: with the trajectory's own condition (in a copy
task the target *is* the condition), with another trajectory's condition (the batch rolled by one) and with
the null condition (classifier-free guidance's unconditional pass). ``own`` far below ``null`` at a ``t``
means the condition decides the output there. Every error is also given as the error of the ``x_0`` it
implies, ``E|x0_hat - x0|^2`` per dimension: an ``eps`` error is divided by ``abar_t / (1 - abar_t)``
there, which at large ``t`` (the sampler's first steps, where a sample's overall shape is set) turns a
small ``eps`` error into a large ``x_0`` one. The EMA weights are read, as the sampler uses them.

The targets here are the trajectories themselves (a copy reading): for a diffuser trained on FTB's block
pairs ``own`` is not its training loss, but the gap between ``own`` and ``shuffled`` still tells whether
the condition reaches the output. JSON with command, config, commit and machine::

    python bench/condition_use.py --run-dir RUN --checkpoint WORK/diffuser_last.pt --stride 5 --hold \
        --out bench/results/condition_use/NAME.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flow_diagnostics import load_run  # noqa: E402

from torchrl_ftb.data import coarsen_trajectories, hold_last_step  # noqa: E402
from torchrl_ftb.diffusion import load_diffuser  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402

TIMESTEPS = (50, 200, 500, 800, 950)


@torch.no_grad()
def condition_use(diffuser, trajectories, *, timesteps=TIMESTEPS, seed: int = 0) -> dict[str, dict[str, float]]:
    """Per timestep: the denoiser's mean squared error to its training target (``eps``, ``x0`` or ``v``
    by the diffuser's prediction type) on the data dims of valid steps, with the trajectories' own condition,
    a rolled one and the null one, each also as the implied ``x_0`` error (see the module docstring)."""
    d = diffuser
    nets = d.sampling_networks(True)
    mask = trajectories["mask"].bool()
    raw = d.raw_data_from_td(trajectories, name="trajectories")
    x0 = d.model_input(raw, mask)
    emb, cmask = d.encode_condition(d.condition_input(raw, mask), mask,
                                    score=d.condition_score(trajectories), networks=nets)
    null_emb, null_mask = nets["encoder"].null(emb.shape[0], emb.shape[1])
    roll = torch.roll(torch.arange(emb.shape[0]), 1)
    conditions = {"own": (emb, cmask), "shuffled": (emb[roll], cmask[roll]), "null": (null_emb, null_mask)}
    valid = mask[..., None].expand(*mask.shape, x0.shape[-1] - 1)
    out = {}
    for t_value in timesteps:
        gen = torch.Generator().manual_seed(seed + int(t_value))
        noise = torch.randn(x0.shape, generator=gen)
        t = torch.full((x0.shape[0],), int(t_value), dtype=torch.long)
        x_t = d.process.add_noise(x0, noise, t)
        target = d.process.training_target(x0, noise, t)
        abar = float(d.process.scheduler.alphas_cumprod[int(t_value)])
        row = {"abar": abar}
        for name, (e, m) in conditions.items():
            output = nets["backbone"](x_t, t, e, m).float()
            eps = d.process.to_eps(x_t, output, t)
            x0_hat = (x_t - (1 - abar) ** 0.5 * eps) / abar ** 0.5
            row[name] = float(((output - target)[..., :-1][valid] ** 2).mean())
            row[f"{name}_x0"] = float(((x0_hat - x0)[..., :-1][valid] ** 2).mean())
        out[str(int(t_value))] = row
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run-dir", type=Path, required=True, help="an FTB run directory (its dataset)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="a diffuser checkpoint (default: the run's own diffuser_last.pt)")
    parser.add_argument("--stride", type=int, default=1, help="the checkpoint models every STRIDE-th step")
    parser.add_argument("--hold", action="store_true", help="the checkpoint models held trajectories")
    parser.add_argument("--num", type=int, default=256, help="trajectories read (a seeded random subset)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    ckpt = args.checkpoint or args.run_dir / "checkpoints" / "diffuser" / "diffuser_last.pt"
    diffuser = load_diffuser(ckpt)
    if diffuser.unconditional:
        parser.error(f"{ckpt}: an unconditional diffuser has no condition to read")
    if diffuser.score_condition:
        parser.error(f"{ckpt}: score-conditioned diffusers are not read here (their conditions need s_psi)")
    _, trajs = load_run(args.run_dir)
    if args.hold:
        trajs = hold_last_step(trajs)
    if args.stride > 1:
        trajs = coarsen_trajectories(trajs, args.stride).contiguous()
    if diffuser.horizon is not None and trajs.batch_size[1] != diffuser.horizon:
        parser.error(f"{ckpt}: a diffuser of horizon {diffuser.horizon}, the trajectories have "
                     f"{trajs.batch_size[1]} steps (check --stride)")
    pick = torch.randperm(trajs.batch_size[0], generator=torch.Generator().manual_seed(args.seed))[:args.num]
    result = condition_use(diffuser, trajs[pick], seed=args.seed)
    record = {**run_record(config={**vars(args), "checkpoint": str(ckpt), "prediction_type":
                                   diffuser.process.prediction_type, "diffuser_config": diffuser.config}),
              "checkpoint_step": int(torch.load(ckpt, weights_only=True).get("step", -1)), "by_timestep": result}
    write_json(args.out, record)
    for t, row in result.items():
        print(f"t={t}: own {row['own']:.3f} shuffled {row['shuffled']:.3f} null {row['null']:.3f} | x0: own "
              f"{row['own_x0']:.3f} shuffled {row['shuffled_x0']:.3f} null {row['null_x0']:.3f}")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
