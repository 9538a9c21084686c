"""The diffusion process: cosine schedule, T=1000, epsilon (or x0, or v) prediction, and samplers.

Schedules and sampler updates come from ``diffusers`` (well-kept, tested maths) rather than
being hand-written:

* training noise: :meth:`diffusers.DDPMScheduler.add_noise` with
  ``beta_schedule="squaredcos_cap_v2"`` (the cosine schedule of Nichol & Dhariwal);
* ``"ddpm"``: ancestral sampling, :class:`~diffusers.DDPMScheduler` with
  ``variance_type="fixed_small"`` — the added noise is scaled by the posterior *standard
  deviation* (the authors' code scales it by the variance, a bug);
* ``"ddim"``: :class:`~diffusers.DDIMScheduler` with ``eta=0`` (deterministic);
* ``"dpm++"``: :class:`~diffusers.DPMSolverMultistepScheduler` (2nd-order DPM-Solver++).

Denoised-sample clipping: with the cosine schedule ``abar_{T-1} ~ 0``, so the first steps
divide the denoiser's error by ``sqrt(abar_t)`` and, unclipped, samples explode (measured:
|x| ~ 1e4 from an untrained net, and a trained toy model collapsing to one output whatever
the sampler). Like Janner et al.'s ``clip_denoised`` we clamp the predicted ``x_0`` to given
per-dimension bounds (the diffuser passes the data's z-range plus a margin) and convert back
to the equivalent ``eps``; this is done here, once for all three samplers, because diffusers'
DPM-Solver++ only offers image-style dynamic thresholding (which rescales). A model that predicts ``x_0``
(``prediction_type="sample"``, Janner et al.'s ``predict_epsilon=False``) has its output turned into the
equivalent ``eps`` first, so clipping, guidance and all three samplers are shared. Each sampler step calls the
denoiser exactly once (classifier-free guidance batches both passes in that one call), so
``steps`` is also the number of denoiser calls.

Example:
    >>> import torch
    >>> process = DiffusionProcess()
    >>> x = process.sample(lambda x, t: torch.zeros_like(x), (2, 4, 3), sampler="ddim", steps=5,
    ...                    generator=torch.Generator().manual_seed(0))
    >>> x.shape
    torch.Size([2, 4, 3])
"""
from __future__ import annotations

from typing import Callable

import torch
from diffusers import DDIMScheduler, DDPMScheduler, DPMSolverMultistepScheduler
from diffusers.utils.torch_utils import randn_tensor
from tqdm.auto import tqdm

__all__ = ["DiffusionProcess", "SAMPLERS"]

SAMPLERS = ("ddpm", "ddim", "dpm++")


class DiffusionProcess:
    """Forward noising and reverse sampling of a diffusion model that predicts ``eps``, ``x_0`` or ``v``.

    Args:
        num_train_timesteps: ``T`` (paper: 1000).
        beta_schedule: a diffusers schedule name (default cosine, ``"squaredcos_cap_v2"``).
        timestep_spacing: diffusers' spacing of the sampler's timesteps. ``"leading"`` (default)
            starts a ``k``-step sampler at ``T - T/k``; ``"trailing"`` starts at ``T - 1``, where
            the cosine schedule's ``abar ~ 2e-9``: the ``x_0`` an epsilon-model implies there is its
            error times ``1/sqrt(abar) ~ 2e4``, which the clip pins to the data bounds and the chain
            never recovers from (measured on button-press-v3, cpu preset, DDPM-25, 8 top-return
            conditions of length 500: generated lengths 3-54 with "trailing", 5 of 8 full-length
            with "leading"). Trailing spacing is meant for zero-terminal-SNR *v*-prediction models.
        prediction_type: what the denoiser outputs and is trained on: ``"epsilon"`` (default; the
            paper and the authors' code), ``"sample"`` (the clean ``x_0``; Janner et al.'s Diffuser
            uses it for its locomotion planners) or ``"v_prediction"`` (``v = sqrt(abar) eps -
            sqrt(1 - abar) x_0``, Salimans & Ho 2022: ``eps``-like at small ``t``, ``x_0``-like at large
            ``t``, where an ``eps`` loss barely sees the ``x_0`` the sampler's first steps divide out of
            it). The loss is the MSE to :meth:`training_target`; samplers see :meth:`to_eps` of the output.
    """

    PREDICTION_TYPES = ("epsilon", "sample", "v_prediction")

    def __init__(self, *, num_train_timesteps: int = 1000, beta_schedule: str = "squaredcos_cap_v2",
                 timestep_spacing: str = "leading", prediction_type: str = "epsilon") -> None:
        if timestep_spacing not in ("leading", "trailing", "linspace"):
            raise ValueError(f"timestep_spacing must be 'leading', 'trailing' or 'linspace', got {timestep_spacing!r}")
        if prediction_type not in self.PREDICTION_TYPES:
            raise ValueError(f"prediction_type must be one of {self.PREDICTION_TYPES}, got {prediction_type!r}")
        self.num_train_timesteps = int(num_train_timesteps)
        self.beta_schedule = beta_schedule
        self.timestep_spacing = timestep_spacing
        self.prediction_type = prediction_type
        self.scheduler = DDPMScheduler(
            num_train_timesteps=self.num_train_timesteps,
            beta_schedule=beta_schedule,
            prediction_type="epsilon",
            variance_type="fixed_small",
            clip_sample=False,
        )

    def config(self) -> dict:
        """JSON-able constructor arguments."""
        return {"num_train_timesteps": self.num_train_timesteps, "beta_schedule": self.beta_schedule,
                "timestep_spacing": self.timestep_spacing, "prediction_type": self.prediction_type}

    def sample_timesteps(self, batch: int, *, device: torch.device | str | None = None,
                         generator: torch.Generator | None = None) -> torch.Tensor:
        """Uniform training timesteps ``t ~ U{0, ..., T-1}``, ``int64 [batch]``."""
        t = torch.randint(0, self.num_train_timesteps, (batch,), generator=generator,
                          device=generator.device if generator is not None else device)
        return t.to(device) if device is not None else t

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) noise`` (per-sample ``t``)."""
        return self.scheduler.add_noise(x0, noise, t)

    def _abar(self, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``abar_t`` per sample, shaped to broadcast against ``x_t``."""
        return self.scheduler.alphas_cumprod.to(x_t.device)[t].view(-1, *([1] * (x_t.ndim - 1)))

    def training_target(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:
        """What the denoiser is regressed on: ``noise`` (epsilon prediction), ``x0`` (sample prediction) or
        ``sqrt(abar_t) noise - sqrt(1 - abar_t) x0`` (v prediction, which needs the timesteps ``t [B]``)."""
        if self.prediction_type == "epsilon":
            return noise
        if self.prediction_type == "sample":
            return x0
        if t is None:
            raise ValueError("training_target: v prediction needs the timesteps t")
        return self.scheduler.get_velocity(x0, noise, t)

    def to_eps(self, x_t: torch.Tensor, output: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The ``eps`` a denoiser ``output`` at ``(x_t, t)`` stands for.

        For sample prediction ``eps = (x_t - sqrt(abar_t) x0) / sqrt(1 - abar_t)``, for v prediction
        ``eps = sqrt(abar_t) v + sqrt(1 - abar_t) x_t``; both affine in the output, so classifier-free
        guidance on ``x0`` or ``v`` equals guidance on ``eps``.
        """
        if self.prediction_type == "epsilon":
            return output
        abar = self._abar(x_t, t)
        if self.prediction_type == "v_prediction":
            return abar.sqrt() * output + (1 - abar).sqrt() * x_t
        return (x_t - abar.sqrt() * output) / (1 - abar).sqrt()

    def make_scheduler(self, sampler: str, steps: int):
        """A fresh diffusers scheduler for ``sampler`` with ``steps`` inference steps set."""
        if sampler not in SAMPLERS:
            raise ValueError(f"unknown sampler {sampler!r}; choose one of {SAMPLERS}")
        steps = int(steps)
        if not 1 <= steps <= self.num_train_timesteps:
            raise ValueError(f"sampler steps must be in [1, {self.num_train_timesteps}], got {steps}")
        common = dict(num_train_timesteps=self.num_train_timesteps, beta_schedule=self.beta_schedule,
                      prediction_type="epsilon")
        if sampler == "ddpm":
            sched = DDPMScheduler(**common, variance_type="fixed_small", clip_sample=False,
                                  timestep_spacing=self.timestep_spacing)
        elif sampler == "ddim":
            sched = DDIMScheduler(**common, clip_sample=False, set_alpha_to_one=True,
                                  timestep_spacing=self.timestep_spacing)
        else:
            sched = DPMSolverMultistepScheduler(**common, algorithm_type="dpmsolver++", solver_order=2,
                                                lower_order_final=True, timestep_spacing=self.timestep_spacing)
        sched.set_timesteps(steps)
        return sched

    def _edit_eps(self, x_t: torch.Tensor, eps: torch.Tensor, t: torch.Tensor,
                  bounds: tuple[torch.Tensor, torch.Tensor] | None,
                  x0_guide: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None) -> torch.Tensor:
        """``eps`` whose implied ``x_0`` is first moved by ``x0_guide(x_0, abar_t)`` (if given), then clamped
        to ``bounds`` (if given)."""
        abar = self._abar(x_t, t)
        a, s = abar.sqrt(), (1 - abar).sqrt()
        x0 = (x_t - s * eps) / a
        if x0_guide is not None:
            x0 = x0_guide(x0, abar)
            if tuple(x0.shape) != tuple(x_t.shape):
                raise ValueError(f"sample: x0_guide returned shape {list(x0.shape)}, expected {list(x_t.shape)}")
        if bounds is not None:
            x0 = x0.clamp(bounds[0], bounds[1])
        return (x_t - a * x0) / s

    @torch.no_grad()
    def sample(
        self,
        denoise: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        shape: tuple,
        *,
        sampler: str = "ddpm",
        steps: int = 50,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        progress: bool = False,
        x0_bounds: tuple[torch.Tensor, torch.Tensor] | None = None,
        x_init: torch.Tensor | None = None,
        strength: float = 1.0,
        known: tuple[torch.Tensor, torch.Tensor] | None = None,
        x0_guide: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Run the reverse process from pure noise, or from a noised ``x_init`` (SDEdit).

        With ``known = (where, values)`` the entries ``where`` are held at ``values`` from the start and
        after every step (inpainting as Janner et al. 2022's Diffuser conditions on the current state:
        the clean value, not a noised one), so e.g. a trajectory starts at a given state.

        With ``x_init`` and ``strength < 1`` (SDEdit, Meng et al. 2022; diffusers' img2img
        ``strength``), the chain runs only the last ``n = max(1, round(strength * steps))`` of
        the sampler's ``steps`` timesteps, starting from ``x_init`` noised to the first of them
        with the training marginal ``q(x_t | x_0 = x_init)``: a small ``strength`` edits
        ``x_init``, ``strength = 1`` ignores it (pure noise, as without ``x_init``).

        Args:
            denoise: ``denoise(x_t [B, ...], t [B])``, the model's output (``eps`` or ``x_0`` by
                ``prediction_type``; guidance already applied).
            shape: sample shape ``[B, H, D]``.
            sampler: ``"ddpm"``, ``"ddim"`` or ``"dpm++"``.
            steps: number of sampler steps (= denoiser calls).
            generator: seeds the initial noise and the DDPM noise.
            device: where to sample.
            progress: show a tqdm bar over the steps.
            x0_bounds: ``(low, high)`` broadcastable to ``shape``: clamp the predicted ``x_0``
                (``None``: no clipping).
            x_init: model-space start ``shape`` for an edit (``None``: pure noise).
            strength: share of the sampler's steps run from the noised ``x_init``, in (0, 1].
            known: ``(where, values)``: a bool mask broadcastable to ``shape`` and model-space values of
                ``shape``; those entries are fixed (``None``: nothing fixed).
            x0_guide: ``x0_guide(x_0, abar_t)`` -> a moved ``x_0`` of the same shape, applied to the
                predicted ``x_0`` at every step before the clip (e.g. a step up an objective's gradient,
                :meth:`TrajectoryDiffuser.generate`'s ``guide``); the sampler then steps with the ``eps`` the
                moved ``x_0`` implies, so its noise stays the scheduler's (``None``: no guide).

        Returns:
            ``x_0`` estimate, float32 ``shape``.
        """
        if not 0.0 < float(strength) <= 1.0:
            raise ValueError(f"sample: strength must be in (0, 1], got {strength}")
        if strength < 1.0 and x_init is None:
            raise ValueError("sample: strength < 1 edits x_init; pass x_init")
        sched = self.make_scheduler(sampler, steps)
        x = randn_tensor(tuple(shape), generator=generator, device=torch.device(device or "cpu"),
                         dtype=torch.float32) * sched.init_noise_sigma
        timesteps = sched.timesteps
        if strength < 1.0:  # x_init is given (checked above)
            if tuple(x_init.shape) != tuple(shape):
                raise ValueError(f"sample: x_init has shape {list(x_init.shape)}, expected {list(shape)}")
            start = len(timesteps) - max(1, round(float(strength) * len(timesteps)))
            timesteps = timesteps[start:]
            if hasattr(sched, "set_begin_index"):  # multistep solvers keep a step index
                sched.set_begin_index(start)
            t0 = timesteps[:1].to(x.device).long().expand(x.shape[0])
            x = self.add_noise(x_init.to(x.device, torch.float32), x, t0)  # x: the drawn noise
        if known is not None:
            where, values = known[0].to(x.device), known[1].to(x.device, torch.float32)
            if tuple(values.shape) != tuple(shape):
                raise ValueError(f"sample: known values have shape {list(values.shape)}, expected {list(shape)}")

            def hold(z: torch.Tensor) -> torch.Tensor:
                return torch.where(where, values, z)
        else:
            def hold(z: torch.Tensor) -> torch.Tensor:
                return z
        x = hold(x)
        for t in tqdm(timesteps, desc=f"sampling ({sampler})", disable=not progress, leave=False):
            t_batch = t.to(x.device).long().expand(x.shape[0])
            eps = self.to_eps(x, denoise(x, t_batch).float(), t_batch)
            if x0_bounds is not None or x0_guide is not None:
                eps = self._edit_eps(x, eps, t_batch, x0_bounds, x0_guide)
            kwargs = {"generator": generator} if sampler == "ddpm" else {}
            if sampler == "ddim":
                kwargs["eta"] = 0.0
            x = hold(sched.step(eps, t, x, **kwargs).prev_sample)
        return x
