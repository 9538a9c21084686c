"""``TrajectoryDiffuser``: wiring of backbone, condition encoder, process, normaliser and EMA.

The diffused vector per step is ``[observation, action]`` (``+ [reward]`` with
``reward_channel=True``, FTB as data augmentation §4.4), z-scored per dimension, plus one
**validity channel**: ``+1`` on valid steps, ``-1`` on padded ones. The generated length is
the prefix that best agrees with the sign of that channel (:meth:`detect_mask`, at least one step). We chose a learned channel
over the authors' ``|obs|+|act| < 1`` heuristic (which breaks for any task whose raw values
are small): its loss is computed on *every* step while the state/action (reward) loss is
masked to valid steps (on every step with ``padding_loss``), and padded target steps are set to 0 (in z-score space) before
noising so their raw values never reach the model.

**Static dimensions** (``static_dims``): data dimensions that are constant over the dataset
(Meta-World pads absent objects with zeros: 15-25 of its 39 observation dims never change in
one task) are not diffused -- they carry no information, yet the denoiser would have to spend
per-step capacity reproducing their noise. They are filled with their constant on decoding.
:func:`~torchrl_ftb.diffusion.make_diffuser` finds them from the data (``data=``).

**Observation structure** (optional, e.g. Meta-World's): ``lagged_dims`` are pairs
``(target, source)`` of observation dimensions with ``obs[t, target] = obs[t - 1, source]``
(a stacked previous frame; at ``t = 0`` the source's own value). Targets are not diffused
but rebuilt from the generated source on decoding, so generated trajectories satisfy the
frame stack exactly. ``time_constant_dims`` (e.g. a goal) are diffused but decoded as their
mean over the valid steps, constant within each trajectory as in the data. Both are off by
default (the paper diffuses the raw observation).

The denoising networks (``backbone`` + ``encoder``, which holds the learned null condition)
live in ``networks``; ``ema`` is a :class:`torch.optim.swa_utils.AveragedModel` copy of them
(updated by :meth:`update_ema`, used by :meth:`generate` by default). The normaliser's
buffers are shared by both.

Example:
    >>> import torch
    >>> from torchrl_ftb.diffusion import make_diffuser
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> data = make_toy_dataset(num_trajectories=8, horizon=8, seed=0)
    >>> diffuser = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=8).fit_normalizer(data)
    >>> out = diffuser.generate(data[:2], sampler="ddim", steps=2, use_ema=False)
    >>> out["observation"].shape, out["mask"].dtype
    (torch.Size([2, 8, 3]), torch.bool)
    >>> TrajectoryDiffuser.detect_mask(torch.tensor([[1.0, 0.9, -0.2, 0.8, -1.0, -0.9]])).sum().item()
    4
"""
from __future__ import annotations

import contextlib
import math
import warnings
from typing import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from torchrl_ftb.data.trajectories import REWARD_KEY
from torchrl_ftb.diffusion.backbones.base import DenoiserBackbone
from torchrl_ftb.diffusion.condition import TrajectoryEncoder
from torchrl_ftb.diffusion.normalizer import TrajectoryNormalizer
from torchrl_ftb.diffusion.process import DiffusionProcess
from torchrl_ftb.preference.score import NORMALIZED_SCORE_KEY

__all__ = ["TrajectoryDiffuser", "REWARD_KEY"]



class TrajectoryDiffuser(nn.Module):
    """Classifier-free conditional trajectory diffuser (FTB §3.1, Fig. 2).

    Args:
        backbone: denoiser, ``transition_dim = obs_dim + action_dim (+1 reward) + 1 validity``.
        encoder: condition encoder over ``obs_dim + action_dim (+1)`` (``None`` iff unconditional).
        process: the diffusion process (schedule + samplers).
        normalizer: z-score over ``obs_dim + action_dim (+1)``.

    Keyword Args:
        obs_dim: observation size.
        action_dim: action size.
        reward_channel: also diffuse the reward (``("next", "reward")``).
        unconditional: no condition at all (SYNTHETIC-style baseline).
        cond_drop_prob: probability of replacing the condition by the null one in training (CFG).
        padding_loss: the training loss also supervises the data channels on padded target steps
            (target 0, the padding); ``False``: the validity channel only there.
        ema_decay: decay of the EMA of the networks.
        horizon: default horizon of generated trajectories (used when no condition is given).
        clip_margin: at sampling, the predicted ``x_0`` is clamped to the data's range (z-space)
            widened by this fraction of its width on each side (observations and reward;
            actions to the data's action range itself, validity channel to [-1, 1]);
            ``None`` disables clipping (see :mod:`torchrl_ftb.diffusion.process`).
        static_dims: indices into ``[obs, action (, reward)]`` that are constant in the data
            and not diffused (filled with the normaliser's mean on decoding).
        lagged_dims: ``(target, source)`` observation-index pairs, ``obs[t, target] =
            obs[t - 1, source]``: targets are not diffused but copied on decoding.
        time_constant_dims: observation indices decoded as their per-trajectory mean.
    """

    def __init__(
        self,
        backbone: DenoiserBackbone,
        encoder: TrajectoryEncoder | None,
        process: DiffusionProcess,
        normalizer: TrajectoryNormalizer,
        *,
        obs_dim: int,
        action_dim: int,
        reward_channel: bool = False,
        unconditional: bool = False,
        cond_drop_prob: float = 0.25,
        padding_loss: bool = False,
        ema_decay: float = 0.995,
        horizon: int | None = None,
        clip_margin: float | None = 0.5,
        static_dims: Sequence[int] = (),
        lagged_dims: Sequence[Sequence[int]] = (),
        time_constant_dims: Sequence[int] = (),
    ) -> None:
        super().__init__()
        self.clip_margin = clip_margin
        self.obs_dim, self.action_dim = int(obs_dim), int(action_dim)
        self.reward_channel = bool(reward_channel)
        static = sorted({int(i) for i in static_dims})
        if static and (static[0] < 0 or static[-1] >= self.data_dim):
            raise ValueError(f"static_dims {static} out of range for {self.data_dim} data dims")
        if len(static) >= self.data_dim:
            raise ValueError("static_dims: at least one data dimension must be diffused")
        self.static_dims = tuple(static)
        self.lagged_dims = self._check_lagged(lagged_dims, obs_dim)
        self.time_constant_dims = tuple(sorted({int(i) for i in time_constant_dims}))
        if self.time_constant_dims and (self.time_constant_dims[0] < 0 or self.time_constant_dims[-1] >= obs_dim):
            raise ValueError(f"time_constant_dims {list(self.time_constant_dims)} out of range for {obs_dim} "
                             "observation dims")
        skipped = set(static) | {t for t, _ in self.lagged_dims}
        if len(skipped) >= self.data_dim:
            raise ValueError("static_dims + lagged_dims: at least one data dimension must be diffused")
        self.register_buffer("diffused_index",
                             torch.tensor([i for i in range(self.data_dim) if i not in skipped]),
                             persistent=False)
        self.unconditional = bool(unconditional)
        if not 0.0 <= cond_drop_prob < 1.0:
            raise ValueError(f"cond_drop_prob must be in [0, 1), got {cond_drop_prob}")
        self.cond_drop_prob = float(cond_drop_prob)
        self.padding_loss = bool(padding_loss)
        self.horizon = horizon
        self.process = process
        if backbone.transition_dim != self.transition_dim:
            raise ValueError(f"backbone.transition_dim={backbone.transition_dim} but the diffuser needs "
                             f"{self.transition_dim} (obs {obs_dim} + action {action_dim}"
                             f"{' + reward 1' if reward_channel else ''} - static/lagged {len(skipped)} + validity 1)")
        if normalizer.dim != self.data_dim:
            raise ValueError(f"normalizer.dim={normalizer.dim} but the data have {self.data_dim} dims")
        if unconditional != (encoder is None):
            raise ValueError("pass encoder=None exactly when unconditional=True")
        if encoder is not None and encoder.transition_dim != self.diffused_dim:
            raise ValueError(f"encoder.transition_dim={encoder.transition_dim} but conditions have "
                             f"{self.diffused_dim} (non-static) dims")
        if encoder is not None and backbone.cond_dim != encoder.embed_dim:
            raise ValueError(f"backbone.cond_dim={backbone.cond_dim} != encoder.embed_dim={encoder.embed_dim}")
        self.normalizer = normalizer
        nets = {"backbone": backbone} if encoder is None else {"backbone": backbone, "encoder": encoder}
        self.networks = nn.ModuleDict(nets)
        self.ema = AveragedModel(self.networks, multi_avg_fn=get_ema_multi_avg_fn(ema_decay), use_buffers=False)
        self.ema.requires_grad_(False)
        self.ema_decay = float(ema_decay)
        #: constructor config (set by :func:`~torchrl_ftb.diffusion.make_diffuser`), for save/load
        self.config: dict | None = None

    # ------------------------------------------------------------------ layout
    @staticmethod
    def _check_lagged(pairs: Sequence[Sequence[int]], obs_dim: int) -> tuple[tuple[int, int], ...]:
        out = tuple(sorted((int(t), int(s)) for t, s in pairs))
        targets = [t for t, _ in out]
        if any(not (0 <= i < obs_dim) for pair in out for i in pair):
            raise ValueError(f"lagged_dims {[list(p) for p in out]}: indices must be observation dims in [0, {obs_dim})")
        if len(set(targets)) != len(targets) or set(targets) & {s for _, s in out}:
            raise ValueError(f"lagged_dims {[list(p) for p in out]}: each target once, and no target may be a source")
        return out

    @property
    def data_dim(self) -> int:
        """Size of ``[obs, action (, reward)]``."""
        return self.obs_dim + self.action_dim + int(self.reward_channel)

    @property
    def diffused_dim(self) -> int:
        """Number of data dimensions that are diffused (``data_dim`` minus static and lagged ones)."""
        return int(self.diffused_index.numel())

    @property
    def transition_dim(self) -> int:
        """Size of the diffused vector (non-static data + validity channel)."""
        return self.diffused_dim + 1

    @property
    def backbone(self) -> DenoiserBackbone:
        return self.networks["backbone"]

    @property
    def score_condition(self) -> bool:
        """Whether conditions carry their normalised score (:data:`NORMALIZED_SCORE_KEY`) into the encoder."""
        return self.encoder is not None and self.encoder.score_condition

    def condition_score(self, condition: TensorDictBase, *, name: str = "condition") -> torch.Tensor | None:
        """The ``[B]`` normalised scores of a condition batch ``[B, H]`` (``None`` unless
        :attr:`score_condition`): the entry itself when it is ``[B]``, its first step when it is
        stored per step ``[B, H]`` (as :func:`~torchrl_ftb.preference.with_normalized_scores` does)."""
        if not self.score_condition:
            return None
        value = condition.get(NORMALIZED_SCORE_KEY, None)
        if value is None:
            raise ValueError(f"{name}: missing {NORMALIZED_SCORE_KEY!r} (the condition's dataset-normalised score), required "
                             "by this diffuser (score_condition=True)")
        value = torch.as_tensor(value)
        batch = condition.batch_size[0]
        if value.shape == condition.batch_size:
            value = value[:, 0]
        if value.shape != (batch,):
            raise ValueError(f"{name}: {NORMALIZED_SCORE_KEY!r} must be [{batch}] or [{batch}, H], got {list(value.shape)}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name}: {NORMALIZED_SCORE_KEY!r} has non-finite values")
        return value.float()

    @property
    def encoder(self) -> TrajectoryEncoder | None:
        return self.networks["encoder"] if "encoder" in self.networks else None

    def trainable_parameters(self):
        """Parameters the optimiser updates (the EMA copy is excluded)."""
        return self.networks.parameters()

    # ------------------------------------------------------------------ data <-> model space
    def raw_data(self, observation: torch.Tensor, action: torch.Tensor,
                 reward: torch.Tensor | None = None, *, name: str = "batch") -> torch.Tensor:
        """Concatenate ``[obs, action (, reward)]`` (raw units), checking sizes."""
        if observation.shape[-1] != self.obs_dim:
            raise ValueError(f"{name}: 'observation' has size {observation.shape[-1]}, expected {self.obs_dim}")
        if action.shape[-1] != self.action_dim:
            raise ValueError(f"{name}: 'action' has size {action.shape[-1]}, expected {self.action_dim}")
        parts = [observation, action]
        if self.reward_channel:
            if reward is None:
                raise ValueError(f"{name}: missing ('next', 'reward'), required with reward_channel=True")
            parts.append(reward.reshape(*observation.shape[:-1], 1))
        return torch.cat([p.float() for p in parts], -1)

    def raw_data_from_td(self, td: TensorDictBase, *, name: str = "batch") -> torch.Tensor:
        """``[obs, action (, reward)]`` of a trajectory batch (conventions' key names)."""
        reward = td.get(REWARD_KEY, None) if self.reward_channel else None
        return self.raw_data(td.get("observation"), td.get("action"), reward, name=name)

    def fit_normalizer(self, trajectories: TensorDictBase) -> "TrajectoryDiffuser":
        """Fit the z-score on the valid steps of a trajectory batch ``[N, H]`` (e.g. the dataset)."""
        if trajectories.batch_dims != 2 or "mask" not in trajectories.keys():
            raise ValueError("fit_normalizer: expected a padded trajectory batch [N, H] with a 'mask'")
        self.normalizer.fit(self.raw_data_from_td(trajectories, name="fit_normalizer").to(self.normalizer.mean.device),
                            trajectories.get("mask").to(self.normalizer.mean.device))
        varying = [i for i in self.static_dims if not bool(self.normalizer.constant[i])]
        if varying:
            raise ValueError(f"fit_normalizer: data dims {varying} were built as static (not diffused) but vary "
                             f"in these trajectories; rebuild with make_diffuser(..., data=trajectories)")
        return self

    def _check_fitted(self) -> None:
        if not self.normalizer.is_fitted:
            raise ValueError("TrajectoryDiffuser: the normalizer is not fitted; call "
                             "diffuser.fit_normalizer(dataset_trajectories) first")

    def model_input(self, raw: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Normalised data (0 on padded steps) + validity channel (+1 valid / -1 padded)."""
        self._check_fitted()
        m = mask.bool()[..., None]
        x = self._diffused(torch.where(m, self.normalizer.normalize(raw), torch.zeros_like(raw)))
        return torch.cat([x, m.float() * 2.0 - 1.0], -1)

    def condition_input(self, raw: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Normalised condition (0 on padded steps)."""
        self._check_fitted()
        return self._diffused(torch.where(mask.bool()[..., None], self.normalizer.normalize(raw), torch.zeros_like(raw)))

    def _diffused(self, z: torch.Tensor) -> torch.Tensor:
        """The diffused (non-static, non-lagged) dimensions of a normalised ``[..., data_dim]`` tensor."""
        if self.diffused_dim == self.data_dim:
            return z
        return z.index_select(-1, self.diffused_index.to(z.device))

    def _full(self, z: torch.Tensor) -> torch.Tensor:
        """Scatter diffused dims ``[..., diffused_dim]`` into ``[..., data_dim]`` (others: z = 0)."""
        if self.diffused_dim == self.data_dim:
            return z
        full = z.new_zeros(*z.shape[:-1], self.data_dim)
        full[..., self.diffused_index.to(z.device)] = z
        return full

    def _model_batch(self, td: TensorDictBase, shape: tuple[int, int], *, name: str,
                     device: torch.device) -> torch.Tensor:
        """Model-space form of a trajectory batch that must be ``shape`` with a ``mask`` (a clear error else)."""
        if tuple(td.batch_size) != tuple(shape) or "mask" not in td.keys():
            raise ValueError(f"generate: {name!r} must be a trajectory batch {list(shape)} with a 'mask', "
                             f"got {list(td.batch_size)}")
        td = td.to(device)
        return self.model_input(self.raw_data_from_td(td, name=name), td.get("mask"))

    def start_known(self, x_source: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(where, values)`` holding a model-space batch's first-step observation (and its validity, +1)
        and, at every step, its time-constant dims at their first-step value (inpainting a start)."""
        data_dim = self.diffused_index.to(x_source.device)
        obs = torch.cat([data_dim < self.obs_dim, torch.ones(1, dtype=torch.bool, device=x_source.device)])
        where = torch.zeros(x_source.shape, dtype=torch.bool, device=x_source.device)
        where[:, 0] = obs
        values = x_source.clone()
        if self.time_constant_dims:
            const = torch.isin(data_dim, torch.tensor(self.time_constant_dims, device=x_source.device))
            const = torch.cat([const, torch.zeros(1, dtype=torch.bool, device=x_source.device)])
            where[:, :, const] = True
            values[:, :, const] = x_source[:, :1, const]
        return where, values

    @staticmethod
    def detect_mask(validity: torch.Tensor) -> torch.Tensor:
        """Prefix mask ``[B, H]`` that best agrees with the validity channel ``[B, H]``.

        The length ``L >= 1`` maximises ``sum_{h<L} v_h - sum_{h>=L} v_h`` with ``v`` clamped
        to [-1, 1], so one stray sign flip does not cut a trajectory short (a plain
        "first negative step" rule does).
        """
        v = validity.float().clamp(-1.0, 1.0)
        agreement = 2 * v.cumsum(-1) - v.sum(-1, keepdim=True)  # score of L = 1..H
        length = agreement.argmax(-1) + 1
        return torch.arange(v.shape[-1], device=v.device) < length[:, None]

    def decode(self, x: torch.Tensor) -> TensorDict:
        """Model-space sample ``[B, H, transition_dim]`` -> trajectory batch (raw units, padded zeros)."""
        mask = self.detect_mask(x[..., -1])
        # static dims sit at z = 0, i.e. their constant (the fitted mean) in raw units
        raw = self.apply_observation_structure(self.normalizer.unnormalize(self._full(x[..., :-1])), mask)
        raw = raw * mask[..., None]
        o, a = self.obs_dim, self.action_dim
        out = {"observation": raw[..., :o], "action": raw[..., o:o + a], "mask": mask}
        if self.reward_channel:
            out["next"] = {"reward": raw[..., o + a:o + a + 1]}
        return TensorDict(out, batch_size=x.shape[:2], device=x.device)

    def apply_observation_structure(self, raw: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Rebuild lagged dims from their sources (one step back) and set time-constant dims to
        their mean over the valid steps, on raw ``[B, H, data_dim]`` data with ``mask [B, H]``."""
        if not (self.lagged_dims or self.time_constant_dims):
            return raw
        raw = raw.clone()
        if self.lagged_dims:
            tgt = torch.tensor([t for t, _ in self.lagged_dims], device=raw.device)
            src = torch.tensor([s for _, s in self.lagged_dims], device=raw.device)
            shifted = torch.cat([raw[:, :1, src], raw[:, :-1, src]], 1)
            raw[..., tgt] = shifted
        if self.time_constant_dims:
            dims = torch.tensor(self.time_constant_dims, device=raw.device)
            w = mask.to(raw.dtype)[..., None]
            mean = (raw[..., dims] * w).sum(1, keepdim=True) / w.sum(1, keepdim=True).clamp_min(1.0)
            raw[..., dims] = mean.expand(-1, raw.shape[1], -1)
        return raw

    def x0_bounds(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Clamp range of denoised samples in model space (``None`` if clipping is off)."""
        if self.clip_margin is None:
            return None
        low, high = self.normalizer.normalized_bounds(self.clip_margin)
        # actions: the data's own range (the env's limits), no margin
        a_low, a_high = self.normalizer.normalized_bounds(0.0)
        acts = slice(self.obs_dim, self.obs_dim + self.action_dim)
        low[acts], high[acts] = a_low[acts], a_high[acts]
        one = torch.ones(1, device=low.device)
        return torch.cat([self._diffused(low), -one]), torch.cat([self._diffused(high), one])

    # ------------------------------------------------------------------ networks
    def encode_condition(self, cond: torch.Tensor, cond_mask: torch.Tensor, *, score: torch.Tensor | None = None,
                         drop: torch.Tensor | None = None,
                         networks: nn.ModuleDict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Encode a normalised condition (``score [B]``: its normalised score, with
        :attr:`score_condition`); ``drop [B]`` True -> null condition."""
        enc = (networks or self.networks)["encoder"]
        emb, mask = enc(cond, cond_mask, score)
        if drop is not None:
            emb, mask = enc.drop(emb, mask, drop)
        return emb, mask

    def guided_eps(self, x_t: torch.Tensor, t: torch.Tensor, cond_emb: torch.Tensor | None,
                   cond_mask: torch.Tensor | None, *, guidance: float,
                   networks: nn.ModuleDict | None = None) -> torch.Tensor:
        """``eps_u + w (eps_c - eps_u)`` with both passes in ONE batched backbone call.

        The outputs are the backbone's (``eps``, or ``x_0`` with ``process.prediction_type="sample"``:
        the same guidance, as the two are affine in each other at fixed ``x_t, t``).
        """
        nets = networks or self.networks
        backbone = nets["backbone"]
        if cond_emb is None or guidance == 1.0:
            return backbone(x_t, t, cond_emb, cond_mask)
        null_emb, null_mask = nets["encoder"].null(cond_emb.shape[0], cond_emb.shape[1])
        eps = backbone(torch.cat([x_t, x_t]), torch.cat([t, t]), torch.cat([cond_emb, null_emb.to(cond_emb.dtype)]),
                       torch.cat([cond_mask, null_mask]))
        eps_c, eps_u = eps.chunk(2)
        return eps_u + guidance * (eps_c - eps_u)

    # ------------------------------------------------------------------ EMA
    @torch.no_grad()
    def update_ema(self) -> None:
        """One EMA step of the networks (the first call copies them)."""
        self.ema.update_parameters(self.networks)

    def set_ema_decay(self, decay: float) -> None:
        """Change the EMA decay used by later :meth:`update_ema` calls."""
        self.ema.multi_avg_fn = get_ema_multi_avg_fn(float(decay))
        self.ema_decay = float(decay)

    def sampling_networks(self, use_ema: bool = True) -> nn.ModuleDict:
        """The EMA networks (default) or the raw ones."""
        if use_ema:
            if int(self.ema.n_averaged) == 0:
                warnings.warn("TrajectoryDiffuser: the EMA was never updated; sampling with the raw weights")
                return self.networks
            return self.ema.module
        return self.networks

    # ------------------------------------------------------------------ sampling
    def objective_guide(self, objective: Callable[[TensorDictBase], torch.Tensor],
                        scale: float) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """The :meth:`DiffusionProcess.sample` ``x0_guide`` of an objective ``J`` (``[B, H]`` batch -> ``[B]``).

        At each sampler step the predicted clean sample moves up the gradient of ``J`` of its decoding::

            g = grad_{x_0} J(decode(x_0));    x_0 <- x_0 + scale * (1 - abar_t) * g / rms(g)

        in model space (z-scored dims), ``rms`` per sample over all its entries (padded steps and the validity
        channel included, whose gradient is zero): ``scale`` is the root-mean-square distance, in the data's standard
        deviations, that a fully noised step moves the sample, whatever the objective's units or scale (a score
        summed over 500 steps has a tiny gradient per entry; any positive rescaling of the objective samples the
        same). The entries that can move move more when they are few (a short detected length; a gradient
        concentrated on one step); the clip to the data's bounds limits them. This is Janner et al.'s (2022) guided
        sampling in ``x_0`` form, with the objective read on the predicted clean sample so no gradient goes
        through the denoiser (one objective forward/backward per step); the ``1 - abar_t`` weight fades the push
        as the noise does, so the last steps are the denoiser's alone. The detected mask and the validity
        channel are not moved.
        """
        scale = float(scale)
        if not math.isfinite(scale) or scale < 0:
            raise ValueError(f"objective_guide: scale must be a finite number >= 0, got {scale}")

        def guide(x0: torch.Tensor, abar: torch.Tensor) -> torch.Tensor:
            with torch.enable_grad():
                z = x0.detach().requires_grad_(True)
                value = objective(self.decode(z))
                if value.shape != z.shape[:1]:
                    raise ValueError(f"generate: the guide objective returned shape {list(value.shape)}, "
                                     f"expected [{z.shape[0]}] (one number per trajectory)")
                if not value.requires_grad:  # the objective does not read the sample (e.g. a constant)
                    return x0
                (grad,) = torch.autograd.grad(value.sum(), z, allow_unused=True)
            if grad is None:
                return x0
            if not bool(torch.isfinite(grad).all()):
                raise FloatingPointError("generate: the guide objective's gradient is NaN/inf")
            grad = grad.to(x0.dtype)
            rms = grad.pow(2).flatten(1).mean(1).sqrt().view(-1, *([1] * (grad.ndim - 1)))
            direction = torch.where(rms > 0, grad / rms.clamp_min(torch.finfo(grad.dtype).tiny), 0.0)
            return x0 + scale * (1 - abar) * direction

        return guide

    @torch.no_grad()
    def generate(
        self,
        condition: TensorDictBase | None = None,
        *,
        num_samples: int | None = None,
        horizon: int | None = None,
        sampler: str = "ddpm",
        steps: int = 50,
        guidance: float = 1.2,
        generator: torch.Generator | None = None,
        use_ema: bool = True,
        autocast_bf16: bool = False,
        progress: bool = False,
        init: TensorDictBase | None = None,
        strength: float = 1.0,
        inpaint_start: bool = False,
        guide: Callable[[TensorDictBase], torch.Tensor] | None = None,
        guide_scale: float = 0.0,
    ) -> TensorDict:
        """Generate trajectories, one per condition (or ``num_samples`` unconditionally).

        With ``init`` and ``strength < 1`` each sample is an SDEdit *edit* of its ``init``
        trajectory (:meth:`DiffusionProcess.sample`): the chain starts from ``init`` noised to
        the ``strength`` share of the sampler's steps instead of from pure noise.

        Args:
            condition: trajectory batch ``[B, Hc]`` (observation, action, mask, reward if
                modelled, :data:`NORMALIZED_SCORE_KEY` with ``score_condition``); required unless the
                model is unconditional.
            num_samples: number of samples for an unconditional model.
            horizon: generated horizon (default: the condition's, else ``self.horizon``).
            sampler: ``"ddpm"``, ``"ddim"`` or ``"dpm++"``.
            steps: sampler steps (= denoiser calls).
            guidance: classifier-free guidance weight ``w`` (paper: 1.2; 1 = conditional only).
            generator: seeds the sampler noise (reproducible samples).
            use_ema: sample with the EMA weights (default).
            autocast_bf16: run the networks under bf16 autocast.
            progress: tqdm bar over sampler steps.
            init: trajectory batch ``[B, H]`` to edit (e.g. the condition itself).
            strength: share of the sampler's steps run from the noised ``init``, in (0, 1]
                (1: pure noise, ``init`` unused).
            inpaint_start: start each sample where its ``init`` (else its condition) starts: the
                first step's observation is held at that trajectory's during sampling
                (:meth:`DiffusionProcess.sample`'s ``known``), and so are the time-constant
                dimensions (the goal, with ``observation_structure``) at every step. Not the paper's
                (its samples start anywhere); a sample of a real start can be replayed in the
                simulator from there.
            guide: a differentiable objective of a decoded trajectory batch, ``[B, H]`` -> ``[B]``
                (e.g. a score model's dataset-normalised score, :func:`~torchrl_ftb.preference.score_objective`).
                With ``guide_scale > 0`` every sampler step moves the predicted clean sample up its
                gradient (:meth:`objective_guide`). Not the paper's (classifier-free only).
            guide_scale: ``lambda`` of that step; 0 (default): no guide.

        Returns:
            Trajectory batch ``[B, H]`` with ``observation``, ``action``, ``mask`` (from the
            validity channel) and ``("next", "reward")`` if modelled.
        """
        if guide_scale and guide is None:
            raise ValueError(f"generate: guide_scale={guide_scale} needs a guide objective")
        self._check_fitted()  # unfitted bounds are +-inf: the unconditional path would decode NaN
        nets = self.sampling_networks(use_ema)
        was_training = nets.training
        nets.eval()
        device = self.normalizer.mean.device
        try:
            ctx = torch.autocast(device.type, dtype=torch.bfloat16) if autocast_bf16 else contextlib.nullcontext()
            cond_emb = cond_mask = None
            if self.unconditional:
                if num_samples is None:
                    num_samples = condition.batch_size[0] if condition is not None else None
                if num_samples is None:
                    raise ValueError("generate: unconditional model needs num_samples (or a condition batch)")
                horizon = horizon or (condition.batch_size[1] if condition is not None else self.horizon)
            else:
                if condition is None:
                    raise ValueError("generate: this diffuser is conditional; pass a 'condition' trajectory batch")
                if condition.batch_dims != 2 or "mask" not in condition.keys():
                    raise ValueError("generate: 'condition' must be a trajectory batch [B, H] with a 'mask'")
                condition = condition.to(device)
                cmask = condition.get("mask").bool()
                cond = self.condition_input(self.raw_data_from_td(condition, name="condition"), cmask)
                score = self.condition_score(condition)
                with ctx:
                    cond_emb, cond_mask = self.encode_condition(cond, cmask, score=score, networks=nets)
                num_samples = condition.batch_size[0]
                horizon = horizon or condition.batch_size[1]
            if horizon is None:
                raise ValueError("generate: unknown horizon; pass horizon=")

            def denoise(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
                with ctx:
                    return self.guided_eps(x_t, t, cond_emb, cond_mask, guidance=guidance, networks=nets)

            x_init = None
            if strength < 1.0:
                if init is None:
                    raise ValueError("generate: strength < 1 edits a trajectory; pass init=")
                x_init = self._model_batch(init, (num_samples, horizon), name="init", device=device)
            known = None
            if inpaint_start:
                source = init if init is not None else condition
                if source is None:
                    raise ValueError("generate: inpaint_start needs the trajectories to start from (init= or a condition)")
                known = self.start_known(self._model_batch(source, (num_samples, horizon), name="inpaint_start",
                                                           device=device))
            x = self.process.sample(denoise, (num_samples, horizon, self.transition_dim), sampler=sampler,
                                    steps=steps, generator=generator, device=device, progress=progress,
                                    x0_bounds=self.x0_bounds(), x_init=x_init, strength=strength, known=known,
                                    x0_guide=self.objective_guide(guide, guide_scale) if guide_scale else None)
        finally:
            nets.train(was_training)
        return self.decode(x)
