"""Named diffuser configurations and the ``make_diffuser`` factory.

Presets differ only in numbers:

* ``"paper"`` — the authors' scale: hidden 128 (the authors' code; the paper's Table 5 says
  256 — pass ``hidden_dim=256``), multipliers [1, 2, 4, 8], attention at every resolution,
  dropout 0.2, condition embedding 128; trained with batch 64, Adam 1e-4, sampled with
  1000-step ancestral DDPM, guidance 1.2. ≈70 M parameters at Meta-World dims.
* ``"cpu"`` — small enough for the whole FTB pipeline on a 2-core CPU: hidden 32,
  multipliers [1, 2, 2, 4] (32/64/64/128 channels, 1.9 M parameters on button-press-v3 with its
  24 constant observation dims left out), cross-attention at the bottleneck only (factor 8),
  no dropout; batch 16, 1,500 steps, ancestral DDPM with 25 steps. Sizing, measured at H=500
  on button-press-v3 (1 thread, the other core busy): 0.75 s per training step; hidden 32 with
  [1, 2, 4, 8] 1.3 s, hidden 24 [1, 2, 4, 8] 0.87 s, [1, 1, 2, 2] 0.60 s; bf16 autocast
  0.79 s (no gain at these widths); held-out eps-MSE after 600 steps 0.08 at t=900,
  0.13 at t=600, 0.22 at t=300 (the previous preset, hidden 16 without the level-0 skip:
  0.85 at every t). Costs are in ``bench/results/diffusion_speed*.json``.
  **Caveat (measured):** on Meta-World (H = 500) a model of this size trained for 1,500 -
  3,000 steps does not follow its condition -- its samples' score, return and length are
  uncorrelated with the condition's (``bench/flow_diagnostics.py``,
  ``bench/diffuser_conditioning.py``), so the flow mostly keeps the original top-k. On the
  toy task the same code follows its condition within 300 steps
  (``tests/test_diffusion_training.py``). ``global_condition=True`` (a pooled condition
  vector added to the timestep embedding) is available; it did not change this at 1,500 steps.
  ``concat_condition=True`` (the condition concatenated to the input, SR3-style) is available:
  on a copy task (target = condition) it makes the condition reach the samples where
  cross-attention alone does not (BENCHMARKS, "A copy task").
  ``score_condition=True`` hands the encoder the condition's normalised score ``ŝ(tau_0)``
  (:class:`~torchrl_ftb.diffusion.TrajectoryEncoder`); conditions then need
  :data:`~torchrl_ftb.preference.NORMALIZED_SCORE_KEY`.
  ``encoder_skip=True`` adds a pointwise linear path to the condition encoder beside its
  GroupNorm-ed convolutions (:class:`~torchrl_ftb.diffusion.TrajectoryEncoder` ``linear_skip``),
  so each condition's own level and scale reach the backbone.
  ``encoder_masked_norm=True`` normalises the encoder's convolutions over each condition's valid steps only
  (:class:`~torchrl_ftb.diffusion.TrajectoryEncoder` ``masked_norm``): by default a short trajectory padded to
  the horizon is normalised mostly by its padding.
  ``padding_loss=True`` also supervises the data channels on padded steps (their clean value is the padding, 0 in
  z-space, and the regression target follows the prediction type; :class:`~torchrl_ftb.diffusion.DiffusionLoss`). By default only the validity channel is supervised there,
  so the denoiser's output on a generated trajectory's padding is unconstrained, while sampling runs every step and
  the convolutions carry it into the last valid steps.
  ``prediction_type="sample"`` trains the backbone to output the clean ``x_0`` instead of the
  noise (Janner et al.'s Diffuser, ``predict_epsilon=False``); sampling, clipping and guidance
  are unchanged (:class:`~torchrl_ftb.diffusion.DiffusionProcess`). **Measured** (cpu preset, 4,500
  steps, Meta-World): its samples score higher under s_psi but their hand dynamics are 5-7x further from
  the data's than eps samples' and they rarely end (BENCHMARKS, "x0 prediction"); default ``"epsilon"``.
  ``prediction_type="v_prediction"`` (Salimans & Ho 2022) is eps-like at small ``t`` and x0-like at large ``t``.
  **Measured** (Meta-World, BENCHMARKS "v prediction"): an eps model's implied ``x_0`` at ``t = 950`` is no better
  with its condition than without (the eps loss barely sees it there), so the sampler's first steps ignore the
  condition; with v the copy task is learned (samples 0.10 from their condition in z-space against 1.19 for eps) and,
  on FTB's pairs, the samples' score follows the condition's block (Spearman +0.44 at 1,500 steps against +0.21).
  Default stays ``"epsilon"`` (the paper's): on the IPL-recipe data v did not raise the flow's stop-rule mean or
  max; on data with room above the top-k it raised the means more than eps (one seed; BENCHMARKS "v prediction on
  data with room"), and on more seeds it raised the means and no max (BENCHMARKS "v prediction on more seeds": its
  top-block samples stay under their conditions' return: about half on drawer-open up to 9,000 steps).
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
from typing import Sequence

import torch
import yaml
from tensordict import TensorDictBase

from torchrl_ftb.diffusion.backbones.unet import TemporalUnet
from torchrl_ftb.diffusion.condition import TrajectoryEncoder
from torchrl_ftb.diffusion.model import TrajectoryDiffuser
from torchrl_ftb.diffusion.normalizer import TrajectoryNormalizer
from torchrl_ftb.diffusion.process import DiffusionProcess

__all__ = ["PRESETS", "get_preset", "make_diffuser", "parse_overrides", "run_settings"]

_MODEL_DEFAULTS = dict(
    hidden_dim=32,
    dim_mults=[1, 2, 4, 8],
    cond_dim=32,
    attention_factors=None,  # None: lowest resolution only
    num_heads=4,
    kernel_size=5,
    dropout=0.0,
    global_condition=False,
    concat_condition=False,
    score_condition=False,
    encoder_skip=False,
    encoder_masked_norm=False,
    padding_loss=False,
    num_train_timesteps=1000,
    beta_schedule="squaredcos_cap_v2",
    prediction_type="epsilon",
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
        "model": dict(_MODEL_DEFAULTS, hidden_dim=32, dim_mults=[1, 2, 2, 4], cond_dim=32, attention_factors=None,
                      dropout=0.0),
        "train": dict(batch_size=16, lr=1e-3, steps=1500, ema_decay=0.995, grad_clip=1.0),
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


def parse_overrides(items: Sequence[str]) -> dict:
    """``["KEY=VALUE", ...]`` (command-line model-field overrides) as ``{KEY: YAML value}``.

    Example:
        >>> parse_overrides(["concat_condition=true", "hidden_dim=16"])
        {'concat_condition': True, 'hidden_dim': 16}

    Raises:
        ValueError: an item without ``=`` or with an empty key.
    """
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"parse_overrides: expected KEY=VALUE, got {item!r}")
        out[key.strip()] = yaml.safe_load(value)
    return out


def run_settings(
    preset: str,
    *,
    steps: int | None = None,
    batch_size: int | None = None,
    lr: float | None = None,
    grad_clip: float | str | None = "preset",
    sampler: str | None = None,
    sample_steps: int | None = None,
    guidance: float | None = None,
) -> dict:
    """Training and sampling numbers of ``preset``, with the given ones in their place.

    ``None`` keeps the preset's number, except ``grad_clip``: ``"preset"`` keeps the preset's,
    ``None`` means no clipping (the authors').

    Example:
        >>> run_settings("cpu", steps=10)["steps"], run_settings("cpu")["sampler"]
        (10, 'ddpm')
    """
    p = get_preset(preset)
    train, sample = p["train"], p["sample"]
    clip = train.get("grad_clip") if grad_clip == "preset" else grad_clip
    return {
        "steps": int(train["steps"] if steps is None else steps),
        "batch_size": int(train["batch_size"] if batch_size is None else batch_size),
        "lr": float(train["lr"] if lr is None else lr),
        "grad_clip": None if clip is None else float(clip),
        "sampler": str(sample["sampler"] if sampler is None else sampler),
        "sample_steps": int(sample["steps"] if sample_steps is None else sample_steps),
        "guidance": float(sample["guidance"] if guidance is None else guidance),
    }


def make_diffuser(
    preset: str = "cpu",
    *,
    obs_dim: int,
    action_dim: int,
    horizon: int,
    reward_channel: bool = False,
    unconditional: bool = False,
    data: TensorDictBase | None = None,
    static_dims: Sequence[int] | None = None,
    lagged_dims: Sequence[Sequence[int]] | None = None,
    time_constant_dims: Sequence[int] | None = None,
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
        data: the dataset's padded trajectories ``[N, H]``: the normaliser is fitted on them and,
            unless ``static_dims`` is given, their constant dimensions are not diffused (see
            :class:`TrajectoryDiffuser`). Without ``data``, call ``fit_normalizer`` yourself.
        static_dims: indices into ``[obs, action (, reward)]`` not to diffuse (default: none, or
            the constant ones of ``data``).
        lagged_dims: ``(target, source)`` observation pairs with ``obs[t, target] =
            obs[t - 1, source]`` (a stacked previous frame): targets are rebuilt, not diffused
            (e.g. :data:`torchrl_ftb.envs.METAWORLD_OBSERVATION_LAYOUT`).
        time_constant_dims: observation dims decoded as their per-trajectory mean (a goal).
        **overrides: any key of the preset's ``model`` section (e.g. ``hidden_dim=64``).

    Returns:
        The diffuser (normaliser fitted iff ``data`` was given), with
        ``diffuser.config`` holding everything needed to rebuild it (see ``load_diffuser``).
    """
    cfg = get_preset(preset)["model"]
    unknown = set(overrides) - set(cfg)
    if unknown:
        raise ValueError(f"make_diffuser: unknown option(s) {sorted(unknown)}; valid: {sorted(cfg)}")
    cfg.update(overrides)
    data_dim = obs_dim + action_dim + int(reward_channel)
    normalizer = TrajectoryNormalizer(data_dim)
    if data is not None:
        if data.batch_dims != 2 or "mask" not in data.keys():
            raise ValueError("make_diffuser: data must be a padded trajectory batch [N, H] with a 'mask'")
        parts = [data.get("observation"), data.get("action")]
        if reward_channel:
            if ("next", "reward") not in data.keys(True):
                raise ValueError("make_diffuser: reward_channel=True but data has no ('next', 'reward')")
            parts.append(data.get(("next", "reward")).reshape(*data.batch_size, 1))
        normalizer.fit(torch.cat([p.float() for p in parts], -1), data.get("mask"))
        if static_dims is None:
            static_dims = normalizer.constant_dims()
    static_dims = sorted({int(i) for i in (static_dims or ())})
    lagged_dims = sorted([int(t), int(src)] for t, src in (lagged_dims or ()))
    time_constant_dims = sorted({int(i) for i in (time_constant_dims or ())})
    diffused = data_dim - len(set(static_dims) | {t for t, _ in lagged_dims})
    # Everything the output knows about x_t per step passes the full-resolution level (hidden *
    # mults[0] channels); fewer channels than diffused dims cap the eps-MSE at ~1 - capacity/dims
    # even at t = T - 1 where eps ~ x_t. (Before level 0's skip was used, the cap was half that:
    # measured eps-MSE 0.85 at every t for the old cpu preset, hidden 16, 44 dims.)
    capacity = cfg["hidden_dim"] * cfg["dim_mults"][0]
    if capacity < diffused + 1:
        warnings.warn(
            f"make_diffuser: the U-Net's full-resolution path carries {capacity} numbers per step "
            f"(hidden_dim*dim_mults[0]) for {diffused + 1} diffused dimensions: a bottleneck "
            f"(eps-MSE floor ~ {1 - capacity / (diffused + 1):.2f}). Use hidden_dim*dim_mults[0] >= "
            f"{diffused + 1}, or pass data= so constant dimensions are not diffused.",
            stacklevel=2,
        )
    cond_dim = None if unconditional else cfg["cond_dim"]
    backbone = TemporalUnet(
        diffused + 1,
        hidden_dim=cfg["hidden_dim"],
        dim_mults=tuple(cfg["dim_mults"]),
        cond_dim=cond_dim,
        attention_factors=cfg["attention_factors"],
        num_heads=cfg["num_heads"],
        kernel_size=cfg["kernel_size"],
        dropout=cfg["dropout"],
        global_condition=cfg["global_condition"],
        concat_condition=cfg["concat_condition"],
    )
    encoder = None if unconditional else TrajectoryEncoder(diffused, embed_dim=cfg["cond_dim"],
                                                           kernel_size=cfg["kernel_size"],
                                                           score_condition=cfg["score_condition"],
                                                           linear_skip=cfg["encoder_skip"],
                                                           masked_norm=cfg["encoder_masked_norm"])
    diffuser = TrajectoryDiffuser(
        backbone,
        encoder,
        DiffusionProcess(num_train_timesteps=cfg["num_train_timesteps"], beta_schedule=cfg["beta_schedule"],
                         prediction_type=cfg["prediction_type"]),
        normalizer,
        obs_dim=obs_dim,
        action_dim=action_dim,
        reward_channel=reward_channel,
        unconditional=unconditional,
        cond_drop_prob=cfg["cond_drop_prob"],
        padding_loss=cfg["padding_loss"],
        ema_decay=cfg["ema_decay"],
        horizon=horizon,
        clip_margin=cfg["clip_margin"],
        static_dims=static_dims,
        lagged_dims=lagged_dims,
        time_constant_dims=time_constant_dims,
    )
    diffuser.config = {"preset": preset, "obs_dim": int(obs_dim), "action_dim": int(action_dim),
                       "horizon": int(horizon), "reward_channel": bool(reward_channel),
                       "unconditional": bool(unconditional), "static_dims": list(static_dims),
                       "lagged_dims": lagged_dims, "time_constant_dims": time_constant_dims,
                       "global_condition": bool(cfg["global_condition"]),
                       "concat_condition": bool(cfg["concat_condition"]),
                       "score_condition": bool(cfg["score_condition"]),
                       "encoder_skip": bool(cfg["encoder_skip"]),
                       # the whole resolved model section, not only the overrides: a checkpoint rebuilds the model
                       # it was trained as even if the preset is retuned later (schedule, prediction type, ...)
                       **{k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()}}
    return diffuser
