"""``DiffusionSampler``: the trajectory diffuser as a TensorDict module ``"condition" -> "sample"``.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_ftb.diffusion import DiffusionSampler, make_diffuser
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> data = make_toy_dataset(num_trajectories=8, horizon=8, seed=0)
    >>> diffuser = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=8).fit_normalizer(data)
    >>> diffuser.update_ema()
    >>> module = DiffusionSampler(diffuser, sampler="ddim", steps=3, seed=0)
    >>> out = module(TensorDict({"condition": data[:2]}, batch_size=[2]))
    >>> out["sample", "observation"].shape
    torch.Size([2, 8, 3])
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from torchrl_ftb.diffusion.model import REWARD_KEY, TrajectoryDiffuser
from torchrl_ftb.preference.score import NORMALIZED_SCORE_KEY
from torchrl_ftb.diffusion.process import SAMPLERS

__all__ = ["DiffusionSampler"]


def _join(prefix: NestedKey, key: NestedKey) -> tuple:
    p = prefix if isinstance(prefix, tuple) else (prefix,)
    k = key if isinstance(key, tuple) else (key,)
    return (*p, *k)


class DiffusionSampler(TensorDictModuleBase):
    """Generate one trajectory per condition: reads ``condition_key`` ``[B, H]``, writes ``sample_key`` ``[B, H]``.

    Args:
        diffuser: a trained :class:`TrajectoryDiffuser` (its EMA weights are used by default).

    Keyword Args:
        sampler: ``"ddpm"``, ``"ddim"`` or ``"dpm++"``.
        steps: sampler steps (= denoiser calls per generated batch).
        guidance: classifier-free guidance weight ``w`` (paper: 1.2).
        seed: if given, every call restarts from this seed (same input -> same samples).
        generator: a generator to draw from across calls (ignored when ``seed`` is given).
        autocast_bf16: run the networks under bf16 autocast.
        use_ema: sample with the EMA weights (default True).
        max_batch: split large batches into chunks of at most this many conditions.
        condition_key: input sub-td key. Default ``"condition"``.
        sample_key: output sub-td key. Default ``"sample"``.
        num_samples: for an unconditional diffuser without a condition in the input: how many.
        progress: tqdm bar over sampler steps.
        strength: SDEdit strength in (0, 1]: below 1 each sample is an edit of its condition
            (the chain starts from the condition noised to that share of the ``steps``;
            :meth:`TrajectoryDiffuser.generate`). 1 (default, the paper): from pure noise.
        inpaint_start: each sample starts where its condition starts (its first observation, and
            the goal with ``observation_structure``, held during sampling;
            :meth:`TrajectoryDiffuser.generate`). False (default, the paper): anywhere.
        guide: a differentiable objective ``[B, H]`` batch -> ``[B]`` (e.g.
            :func:`~torchrl_ftb.preference.score_objective`) that ``guide_scale > 0`` pushes every sample up
            (:meth:`TrajectoryDiffuser.objective_guide`). Not the paper's.
        guide_scale: ``lambda`` of that push; 0 (default): none.
    """

    def __init__(
        self,
        diffuser: TrajectoryDiffuser,
        *,
        sampler: str = "ddpm",
        steps: int = 50,
        guidance: float = 1.2,
        seed: int | None = None,
        generator: torch.Generator | None = None,
        autocast_bf16: bool = False,
        use_ema: bool = True,
        max_batch: int | None = None,
        condition_key: NestedKey = "condition",
        sample_key: NestedKey = "sample",
        num_samples: int | None = None,
        progress: bool = False,
        strength: float = 1.0,
        inpaint_start: bool = False,
        guide: Callable[[TensorDictBase], torch.Tensor] | None = None,
        guide_scale: float = 0.0,
    ) -> None:
        super().__init__()
        guide_scale = float(guide_scale)
        if not math.isfinite(guide_scale) or guide_scale < 0:
            raise ValueError(f"DiffusionSampler: guide_scale must be a finite number >= 0, got {guide_scale}")
        if guide_scale and guide is None:
            raise ValueError(f"DiffusionSampler: guide_scale={guide_scale} needs a guide objective")
        self.guide, self.guide_scale = guide, guide_scale
        if sampler not in SAMPLERS:
            raise ValueError(f"DiffusionSampler: unknown sampler {sampler!r}; choose one of {SAMPLERS}")
        if not 0.0 < float(strength) <= 1.0:
            raise ValueError(f"DiffusionSampler: strength must be in (0, 1], got {strength}")
        if strength < 1.0 and diffuser.unconditional:
            raise ValueError("DiffusionSampler: strength < 1 edits the condition; this diffuser is unconditional")
        if inpaint_start and diffuser.unconditional:
            raise ValueError("DiffusionSampler: inpaint_start starts each sample where its condition starts; "
                             "this diffuser is unconditional")
        self.strength = float(strength)
        self.inpaint_start = bool(inpaint_start)
        self.diffuser = diffuser
        self.sampler, self.steps, self.guidance = sampler, int(steps), float(guidance)
        self.seed, self.generator = seed, generator
        self.autocast_bf16, self.use_ema = bool(autocast_bf16), bool(use_ema)
        self.max_batch = max_batch
        self.condition_key, self.sample_key = condition_key, sample_key
        self.num_samples = num_samples
        self.progress = progress
        fields = ["observation", "action"] + ([REWARD_KEY] if diffuser.reward_channel else [])
        cond_fields = [*fields, "mask"] + ([NORMALIZED_SCORE_KEY] if diffuser.score_condition else [])
        self.in_keys = [] if diffuser.unconditional else [_join(condition_key, k) for k in cond_fields]
        self.out_keys = [_join(sample_key, k) for k in [*fields, "mask"]]

    def _generator(self) -> torch.Generator | None:
        if self.seed is None:
            return self.generator
        return torch.Generator(device=self.diffuser.normalizer.mean.device).manual_seed(int(self.seed))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        cond = tensordict.get(self.condition_key, None)
        if cond is None and not self.diffuser.unconditional:
            raise ValueError(f"DiffusionSampler: input has no {self.condition_key!r} trajectory batch")
        gen = self._generator()
        opts = dict(sampler=self.sampler, steps=self.steps, guidance=self.guidance, generator=gen,
                    use_ema=self.use_ema, autocast_bf16=self.autocast_bf16, progress=self.progress,
                    guide=self.guide, guide_scale=self.guide_scale)
        if cond is None:
            n = self.num_samples or (tensordict.batch_size[0] if tensordict.batch_dims else None)
            sample = self.diffuser.generate(None, num_samples=n, **opts)
        else:
            chunk = self.max_batch or cond.batch_size[0]
            parts = [self.diffuser.generate(cond[i:i + chunk], init=cond[i:i + chunk], strength=self.strength,
                                            inpaint_start=self.inpaint_start, **opts)
                     for i in range(0, cond.batch_size[0], chunk)]
            sample = torch.cat(parts, 0) if len(parts) > 1 else parts[0]
        if tensordict.device is not None:
            sample = sample.to(tensordict.device)
        tensordict.set(self.sample_key, sample)
        return tensordict
