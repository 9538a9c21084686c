"""Named diffuser configurations and the ``make_diffuser`` factory.

Presets differ only in numbers:

* ``"paper"`` — the authors' scale: hidden 128 (the authors' code; the paper's Table 5 says
  256 — pass ``hidden_dim=256``), multipliers [1, 2, 4, 8], attention at every resolution,
  dropout 0.2, condition embedding 128; trained with batch 64, Adam 1e-4, sampled with
  1000-step ancestral DDPM, guidance 1.2. ≈70 M parameters at Meta-World dims.
* ``"cpu"`` — small enough for the whole FTB pipeline on a 2-core CPU: hidden 16,
  multipliers [1, 2, 4, 8] (16/32/64/128 channels, 2.2 M parameters at Meta-World dims),
  cross-attention at the bottleneck only (factor 8), no dropout; batch 16, 2,000 steps,
  ancestral DDPM with 25 steps. Measured on the 2-core CPU at H=500 (Meta-World): 0.31 s per
  training step at batch 16 (hidden 32: 0.57 s; batch 32: 1.4 s — super-linear on this CPU),
  1.2 s per denoiser call over 100 trajectories with batched guidance. bf16 autocast was
  slower here (small channels). Costs are in ``bench/results/diffusion_speed*.json``.
  Why DDPM and not DPM-Solver++/DDIM by default: on the toy task a briefly trained model
  sampled with the deterministic solvers gave clearly worse trajectories (toy, 400 steps:
  block-0 conditions -> mean true return -3.0 with DPM++ 25 / DDIM 25 vs -1.4 with DDPM 50,
  target block mean -1.2; lengths cut short), the stochastic sampler corrects model error.
  Not a sampler bug: with the exact denoiser of a finite data set all three samplers return
  data points with their lengths (``tests/test_diffusion.py``); on the toy model DDIM with
  ``eta=1`` reproduces DDPM's samples exactly (-0.94, full length) while ``eta=0`` gives -3.4
  (the validity channel's x0 estimate keeps the sign of the initial noise down to t=0), and
  the gap shrinks with training (DDIM-50 -3.4 / -1.8 / -1.7 after 400 / 1500 / 4000 steps,
  DDPM-50 -0.9 / -0.7 / -1.1; lengths fully restored by 4000).
* ``"tiny"`` — for unit tests and doctests only.

``get_preset(name)`` returns the full dict (``model``, ``train`` and ``sample`` sections)
so recipes can read training/sampling defaults from the same place.

Example:
    >>> diffuser = make_diffuser("cpu", obs_dim=39, action_dim=4, horizon=500)
    >>> diffuser.transition_dim
    44
    >>> make_diffuser("cpu", obs_dim=3, action_dim=2, horizon=16, hidden_dim=8).config["hidden_dim"]
    8
"""
from __future__ import annotations

import copy
import warnings

from torchrl_ftb.diffusion.backbones.unet import TemporalUnet
from torchrl_ftb.diffusion.condition import TrajectoryEncoder
from torchrl_ftb.diffusion.model import TrajectoryDiffuser
from torchrl_ftb.diffusion.normalizer import TrajectoryNormalizer
from torchrl_ftb.diffusion.process import DiffusionProcess

__all__ = ["PRESETS", "get_preset", "make_diffuser"]

_MODEL_DEFAULTS = dict(
    hidden_dim=32,
    dim_mults=[1, 2, 4, 8],
    cond_dim=32,
    attention_factors=None,  # None: lowest resolution only
    num_heads=4,
    kernel_size=5,
    dropout=0.0,
    num_train_timesteps=1000,
    beta_schedule="squaredcos_cap_v2",
    cond_drop_prob=0.25,
    ema_decay=0.995,
    clip_margin=0.5,
)

PRESETS: dict[str, dict] = {
    "paper": {
        "model": dict(_MODEL_DEFAULTS, hidden_dim=128, cond_dim=128, attention_factors=[1, 2, 4, 8], dropout=0.2),
        "train": dict(batch_size=64, lr=1e-4, steps=500_000, ema_decay=0.995, grad_clip=None),
        "sample": dict(sampler="ddpm", steps=1000, guidance=1.2),
    },
    "cpu": {
        "model": dict(_MODEL_DEFAULTS, hidden_dim=16, cond_dim=32, attention_factors=None, dropout=0.0),
        "train": dict(batch_size=16, lr=1e-3, steps=2000, ema_decay=0.995, grad_clip=1.0),
        "sample": dict(sampler="ddpm", steps=25, guidance=1.2),
    },
    "tiny": {
        "model": dict(_MODEL_DEFAULTS, hidden_dim=32, dim_mults=[1, 2], cond_dim=32, attention_factors=None,
                      num_heads=2, kernel_size=5, ema_decay=0.9),
        "train": dict(batch_size=32, lr=3e-3, steps=400, ema_decay=0.9, grad_clip=1.0),
        "sample": dict(sampler="ddpm", steps=50, guidance=1.2),
    },
}


def get_preset(name: str) -> dict:
    """A deep copy of preset ``name`` (sections ``model``, ``train``, ``sample``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown diffuser preset {name!r}; choose one of {sorted(PRESETS)}")
    return copy.deepcopy(PRESETS[name])


def make_diffuser(
    preset: str = "cpu",
    *,
    obs_dim: int,
    action_dim: int,
    horizon: int,
    reward_channel: bool = False,
    unconditional: bool = False,
    **overrides,
) -> TrajectoryDiffuser:
    """Build a :class:`TrajectoryDiffuser` from a preset, with model-field overrides.

    Args:
        preset: ``"paper"``, ``"cpu"`` or ``"tiny"``.
        obs_dim: observation size.
        action_dim: action size.
        horizon: (maximum) trajectory horizon; the default length of unconditional samples.
        reward_channel: also diffuse ``("next", "reward")`` (FTB as data augmentation).
        unconditional: no condition (SYNTHETIC-style baseline).
        **overrides: any key of the preset's ``model`` section (e.g. ``hidden_dim=64``).

    Returns:
        The diffuser (normaliser not fitted yet: call ``fit_normalizer(dataset)``), with
        ``diffuser.config`` holding everything needed to rebuild it (see ``load_diffuser``).
    """
    cfg = get_preset(preset)["model"]
    unknown = set(overrides) - set(cfg)
    if unknown:
        raise ValueError(f"make_diffuser: unknown option(s) {sorted(unknown)}; valid: {sorted(cfg)}")
    cfg.update(overrides)
    data_dim = obs_dim + action_dim + int(reward_channel)
    # Everything the output knows about x_t passes the full-resolution level and, with more than
    # one level, its stride-2 down-sampling (level 0's skip is unused, as in Janner et al.): that
    # is hidden*mults[0] channels per 2 steps, i.e. hidden*mults[0]/2 numbers per step. Fewer than
    # the diffused dims caps the eps-MSE at ~1 - capacity/dims even at t = T - 1 where eps ~ x_t.
    # Measured (learn eps = x_t at t=999, 44 dims, H=64, 600 steps): hidden 16 -> 0.84 (bound 0.82),
    # hidden 48 -> 0.54 (bound 0.45), hidden 96 -> 0.24 and falling; the cpu-preset FTB diffuser
    # (hidden 16, 2,000 steps) scores 0.85 at every t.
    width = cfg["hidden_dim"] * cfg["dim_mults"][0]
    capacity = width // 2 if len(cfg["dim_mults"]) > 1 else width
    if capacity < data_dim + 1:
        warnings.warn(
            f"make_diffuser: the U-Net carries {capacity} numbers per step (hidden_dim*dim_mults[0]"
            f"{'/2' if len(cfg['dim_mults']) > 1 else ''}) for {data_dim + 1} diffused dimensions: a bottleneck "
            f"(eps-MSE floor ~ {1 - capacity / (data_dim + 1):.2f}). Use hidden_dim*dim_mults[0] >= "
            f"{(2 if len(cfg['dim_mults']) > 1 else 1) * (data_dim + 1)}.",
            stacklevel=2,
        )
    cond_dim = None if unconditional else cfg["cond_dim"]
    backbone = TemporalUnet(
        data_dim + 1,
        hidden_dim=cfg["hidden_dim"],
        dim_mults=tuple(cfg["dim_mults"]),
        cond_dim=cond_dim,
        attention_factors=cfg["attention_factors"],
        num_heads=cfg["num_heads"],
        kernel_size=cfg["kernel_size"],
        dropout=cfg["dropout"],
    )
    encoder = None if unconditional else TrajectoryEncoder(data_dim, embed_dim=cfg["cond_dim"],
                                                           kernel_size=cfg["kernel_size"])
    diffuser = TrajectoryDiffuser(
        backbone,
        encoder,
        DiffusionProcess(num_train_timesteps=cfg["num_train_timesteps"], beta_schedule=cfg["beta_schedule"]),
        TrajectoryNormalizer(data_dim),
        obs_dim=obs_dim,
        action_dim=action_dim,
        reward_channel=reward_channel,
        unconditional=unconditional,
        cond_drop_prob=cfg["cond_drop_prob"],
        ema_decay=cfg["ema_decay"],
        horizon=horizon,
        clip_margin=cfg["clip_margin"],
    )
    diffuser.config = {"preset": preset, "obs_dim": int(obs_dim), "action_dim": int(action_dim),
                       "horizon": int(horizon), "reward_channel": bool(reward_channel),
                       "unconditional": bool(unconditional), **overrides}
    return diffuser
