"""Temporal 1-D convolutional U-Net over the horizon (Janner et al. 2022 style, FTB Fig. 2).

Residual temporal blocks (Conv1d + GroupNorm + Mish, timestep embedding injected in every
block), stride-2 down/up-sampling, and multi-head cross-attention from the U-Net features to
the encoded condition trajectory at configurable resolutions.

Choices (see ``docs`` / report): attention is *cross*-attention only (the paper's text; the
authors' code concatenates the condition's K/V in front of the features' own, i.e. joint
self+cross attention). Queries and keys get sinusoidal embeddings of their time index in
original steps, so a feature at step ``h`` can find the condition's step ``h`` (the conv
features alone carry almost no absolute position). By default attention runs only at the
lowest resolution: its cost is ``O(H/f * Hc)`` per block, quadratic in the horizon at full
resolution (``f=1``).

``global_condition=True`` adds a second, global path: the masked mean of the encoded condition
goes through an MLP and is added to the timestep embedding, so it reaches every residual block
(as class labels do in class-conditional diffusion). FTB's training pairs tie a target to its
condition only through their blocks (tau_1 is any trajectory of the next block), a global
property; with attention alone our CPU-sized model learned to ignore the condition (samples'
score, length and return uncorrelated with the condition's, guidance 1.2 vs 3 alike:
``bench/results/flow_diagnostics``). The null condition's pooled vector is its learned token.

``concat_condition=True`` adds a third, local path (SR3 / Palette-style image-to-image
conditioning): the encoded condition, zeroed on its padded steps, and its validity mask are
concatenated to ``x_t`` as extra input channels, step by step. It needs a condition of the
sample's horizon (FTB's pairs and flow have it). The null condition is then the learned token
at step 0 with a mask that is True there only.

Example:
    >>> import torch
    >>> net = TemporalUnet(transition_dim=6, hidden_dim=16, dim_mults=(1, 2, 4), cond_dim=16)
    >>> net(torch.randn(3, 10, 6), torch.randint(0, 1000, (3,)), torch.randn(3, 10, 16),
    ...     torch.ones(3, 10, dtype=torch.bool)).shape
    torch.Size([3, 10, 6])
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from torchrl_ftb.diffusion.backbones.base import DenoiserBackbone, sinusoidal_embedding

__all__ = ["TemporalUnet", "ResidualTemporalBlock", "ConditionCrossAttention", "TimestepEmbedding"]


def _groups(channels: int, max_groups: int = 8) -> int:
    return math.gcd(max_groups, channels)


class Conv1dBlock(nn.Sequential):
    """Conv1d -> GroupNorm -> Mish on ``[B, C, L]``."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int) -> None:
        super().__init__(
            nn.Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(_groups(out_channels), out_channels),
            nn.Mish(),
        )


class TimestepEmbedding(nn.Module):
    """Sinusoidal(dim) -> Linear(dim, 4 dim) -> Mish -> Linear(4 dim, dim) of integer timesteps."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.Mish(), nn.Linear(4 * dim, dim))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(sinusoidal_embedding(t, self.dim))


class ResidualTemporalBlock(nn.Module):
    """Two conv blocks with the timestep embedding added in between, dropout, residual 1x1 conv."""

    def __init__(self, in_channels: int, out_channels: int, *, time_dim: int, kernel_size: int = 5,
                 dropout: float = 0.0) -> None:
        super().__init__()
        self.block1 = Conv1dBlock(in_channels, out_channels, kernel_size)
        self.time_mlp = nn.Sequential(nn.Mish(), nn.Linear(time_dim, out_channels))
        self.dropout = nn.Dropout(dropout)
        self.block2 = Conv1dBlock(out_channels, out_channels, kernel_size)
        self.residual = nn.Conv1d(in_channels, out_channels, 1) if in_channels != out_channels else nn.Identity()

    def forward(self, x: torch.Tensor, t_emb: torch.Tensor) -> torch.Tensor:
        h = self.block1(x) + self.time_mlp(t_emb)[..., None]
        h = self.block2(self.dropout(h))
        return h + self.residual(x)


class ConditionCrossAttention(nn.Module):
    """Pre-norm multi-head cross-attention from features ``[B, C, L]`` to a condition ``[B, Hc, Cc]``.

    Uses :class:`torch.nn.MultiheadAttention` (fused SDPA kernels) with a key-padding mask
    built from the condition's mask; residual output. Identity when the condition is ``None``.

    Args:
        channels: feature channels ``C`` (divisible by ``num_heads``).
        cond_dim: condition embedding size ``Cc``.
        num_heads: attention heads.
        factor: temporal down-sampling factor of the features (for their positions).
    """

    def __init__(self, channels: int, cond_dim: int, *, num_heads: int = 4, factor: int = 1) -> None:
        super().__init__()
        if channels % num_heads:
            raise ValueError(f"attention: channels {channels} not divisible by num_heads {num_heads}")
        self.factor = int(factor)
        self.norm = nn.GroupNorm(_groups(channels), channels)
        self.attn = nn.MultiheadAttention(channels, num_heads, kdim=cond_dim, vdim=cond_dim, batch_first=True)

    def forward(self, h: torch.Tensor, cond_emb: torch.Tensor | None, cond_mask: torch.Tensor | None) -> torch.Tensor:
        if cond_emb is None:
            return h
        channels, length = h.shape[1], h.shape[2]
        # centre of the ``factor`` original steps each feature covers
        q_pos = torch.arange(length, device=h.device) * self.factor + (self.factor - 1) / 2
        q = self.norm(h).transpose(1, 2) + sinusoidal_embedding(q_pos, channels).to(h.dtype)
        k_pos = torch.arange(cond_emb.shape[1], device=h.device)
        k = cond_emb + sinusoidal_embedding(k_pos, cond_emb.shape[-1]).to(cond_emb.dtype)
        pad = None if cond_mask is None else ~cond_mask
        out, _ = self.attn(q, k, cond_emb, key_padding_mask=pad, need_weights=False)
        return h + out.transpose(1, 2)


def _masked_mean(emb: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of ``emb [B, L, C]`` over the steps where ``mask [B, L]`` is True (all if None)."""
    if mask is None:
        return emb.mean(1)
    w = mask.to(emb.dtype)[..., None]
    return (emb * w).sum(1) / w.sum(1).clamp_min(1.0)


class _NoAttention(nn.Module):
    """Placeholder where a level has no attention (keeps the block layout uniform)."""

    def forward(self, h: torch.Tensor, *_: object) -> torch.Tensor:
        return h


class TemporalUnet(DenoiserBackbone):
    """Temporal U-Net denoiser ``eps(x_t, t, condition)`` (see module docstring).

    Args:
        transition_dim: per-step size ``D`` of the diffused vector.
        hidden_dim: channels of the first level (paper Table 5: 256; authors' code: 128).
        dim_mults: channel multipliers per level (``len(dim_mults) - 1`` down-samplings).
        cond_dim: size of the encoded condition (``None``: no attention blocks at all).
        attention_factors: down-sampling factors (1 = full length, 2, 4, ...) at which a
            cross-attention block follows the first residual block of a level (and of the
            mid block when it includes the lowest factor). ``None``: lowest resolution only.
        num_heads: attention heads.
        kernel_size: temporal convolution kernel.
        dropout: dropout inside residual blocks (paper: 0.2).
        global_condition: also add an MLP of the condition's masked mean embedding to the
            timestep embedding of every block (see module docstring).
        concat_condition: also concatenate the encoded condition and its mask to the input,
            step by step (see module docstring).
    """

    def __init__(
        self,
        transition_dim: int,
        *,
        hidden_dim: int = 32,
        dim_mults: Sequence[int] = (1, 2, 4, 8),
        cond_dim: int | None = None,
        attention_factors: Sequence[int] | None = None,
        num_heads: int = 4,
        kernel_size: int = 5,
        dropout: float = 0.0,
        global_condition: bool = False,
        concat_condition: bool = False,
    ) -> None:
        super().__init__(transition_dim, cond_dim)
        levels = len(dim_mults)
        if levels < 1:
            raise ValueError("TemporalUnet: dim_mults must not be empty")
        lowest = 2 ** (levels - 1)
        self.horizon_multiple = lowest
        factors = {lowest} if attention_factors is None else {int(f) for f in attention_factors}
        allowed = {2**i for i in range(levels)}
        if not factors <= allowed:
            raise ValueError(f"TemporalUnet: attention_factors {sorted(factors)} must be within {sorted(allowed)}")
        self.attention_factors = tuple(sorted(factors)) if cond_dim is not None else ()
        time_dim = hidden_dim
        self.time_embedding = TimestepEmbedding(time_dim)
        self.global_condition = bool(global_condition) and cond_dim is not None
        if self.global_condition:
            self.condition_mlp = nn.Sequential(nn.Linear(cond_dim, 4 * time_dim), nn.Mish(),
                                               nn.Linear(4 * time_dim, time_dim))
        dims = [hidden_dim * m for m in dim_mults]
        res = dict(time_dim=time_dim, kernel_size=kernel_size, dropout=dropout)

        def attention(channels: int, factor: int) -> nn.Module:
            if cond_dim is None or factor not in factors:
                return _NoAttention()
            return ConditionCrossAttention(channels, cond_dim, num_heads=num_heads, factor=factor)

        self.concat_condition = bool(concat_condition) and cond_dim is not None
        extra = cond_dim + 1 if self.concat_condition else 0  # condition channels + its mask
        self.input_proj = nn.Conv1d(transition_dim + extra, hidden_dim, 1)
        self.downs = nn.ModuleList()
        in_dim = hidden_dim
        for i, out_dim in enumerate(dims):
            self.downs.append(nn.ModuleList([
                ResidualTemporalBlock(in_dim, out_dim, **res),
                attention(out_dim, 2**i),
                ResidualTemporalBlock(out_dim, out_dim, **res),
                nn.Conv1d(out_dim, out_dim, 3, stride=2, padding=1) if i < levels - 1 else nn.Identity(),
            ]))
            in_dim = out_dim
        self.mid = nn.ModuleList([
            ResidualTemporalBlock(dims[-1], dims[-1], **res),
            attention(dims[-1], lowest),
            ResidualTemporalBlock(dims[-1], dims[-1], **res),
        ])
        # Every level's skip is used, level 0's included: Janner et al.'s U-Net drops it, which leaves
        # the output only hidden*mults[0]/2 numbers per step (a stride-2 conv) to carry x_t -- an
        # eps-MSE floor of ~1 - that/D we measured at 0.85 for D = 44 (bench/results/
        # diffusion_quality_button-press-v3_old_unet.json). Here the full-resolution path carries hidden_dim.
        self.ups = nn.ModuleList()
        h_dim = dims[-1]
        for i in reversed(range(levels)):  # skip from level i, output at level i - 1 (level 0: none)
            self.ups.append(nn.ModuleList([
                ResidualTemporalBlock(h_dim + dims[i], dims[i], **res),
                attention(dims[i], 2**i),
                ResidualTemporalBlock(dims[i], dims[i], **res),
                nn.ConvTranspose1d(dims[i], dims[i], 4, stride=2, padding=1) if i > 0 else nn.Identity(),
            ]))
            h_dim = dims[i]
        self.output = nn.Sequential(Conv1dBlock(dims[0], dims[0], kernel_size), nn.Conv1d(dims[0], transition_dim, 1))

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        cond_emb: torch.Tensor | None = None,
        cond_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if x.ndim != 3 or x.shape[-1] != self.transition_dim:
            raise ValueError(f"TemporalUnet: x must be [B, H, {self.transition_dim}], got {list(x.shape)}")
        horizon = x.shape[1]
        padded = -(-horizon // self.horizon_multiple) * self.horizon_multiple
        h = F.pad(x.transpose(1, 2), (0, padded - horizon))  # [B, D, H'] zero-padded on the right
        t_emb = self.time_embedding(t.expand(x.shape[0]) if t.ndim == 0 else t)
        if self.global_condition and cond_emb is not None:
            t_emb = t_emb + self.condition_mlp(_masked_mean(cond_emb, cond_mask)).to(t_emb.dtype)
        if self.concat_condition and cond_emb is not None:
            if cond_emb.shape[1] != horizon or cond_mask is None:
                raise ValueError(f"TemporalUnet(concat_condition=True): needs a condition mask and a condition of "
                                 f"the sample's horizon {horizon}, got {cond_emb.shape[1]}")
            valid = cond_mask.to(cond_emb.dtype)[..., None]
            extra = torch.cat([cond_emb * valid, valid], -1).transpose(1, 2).to(h.dtype)
            h = torch.cat([h, F.pad(extra, (0, padded - horizon))], 1)
        h = self.input_proj(h)
        skips = []
        for res1, attn, res2, down in self.downs:
            h = res2(attn(res1(h, t_emb), cond_emb, cond_mask), t_emb)
            skips.append(h)
            h = down(h)
        res1, attn, res2 = self.mid
        h = res2(attn(res1(h, t_emb), cond_emb, cond_mask), t_emb)
        # level i's skip joins the up block at level i (all levels, level 0 included)
        for res1, attn, res2, up in self.ups:
            h = torch.cat([h, skips.pop()], 1)
            h = up(res2(attn(res1(h, t_emb), cond_emb, cond_mask), t_emb))
        return self.output(h)[..., :horizon].transpose(1, 2)
