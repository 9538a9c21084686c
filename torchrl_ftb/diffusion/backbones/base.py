"""The one interface every denoiser backbone implements (U-Net today, room for a transformer).

A backbone predicts the noise ``eps`` of a noisy trajectory ``x_t`` given the diffusion
timestep and an (optional) encoded condition trajectory:

``forward(x [B, H, D], t [B], cond_emb [B, Hc, C] | None, cond_mask [B, Hc] | None) -> eps [B, H, D]``

``cond_mask`` is ``True`` on condition steps that may be attended to (valid steps);
``cond_emb=None`` means "no condition at all" (unconditional model).

Example:
    >>> import torch
    >>> from torchrl_ftb.diffusion.backbones import TemporalUnet
    >>> net = TemporalUnet(transition_dim=5, hidden_dim=8, dim_mults=(1, 2), cond_dim=8)
    >>> eps = net(torch.randn(2, 7, 5), torch.tensor([3, 500]), torch.randn(2, 7, 8), None)
    >>> eps.shape
    torch.Size([2, 7, 5])
"""
from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["DenoiserBackbone", "sinusoidal_embedding"]


def sinusoidal_embedding(positions: torch.Tensor, dim: int, *, max_period: float = 10000.0) -> torch.Tensor:
    """Transformer-style sinusoidal features of (possibly fractional) positions, ``[..., dim]``.

    Example:
        >>> sinusoidal_embedding(torch.arange(3), 4).shape
        torch.Size([3, 4])
    """
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=positions.device, dtype=torch.float32) / half)
    args = positions.float()[..., None] * freqs
    emb = torch.cat([args.sin(), args.cos()], -1)
    if dim % 2:
        emb = torch.nn.functional.pad(emb, (0, 1))
    return emb


class DenoiserBackbone(nn.Module):
    """Base class of denoiser networks (see module docstring for the forward contract).

    Args:
        transition_dim: size ``D`` of the diffused per-step vector.
        cond_dim: size ``C`` of the encoded condition (``None`` for unconditional backbones).
    """

    #: the horizon is padded internally to a multiple of this (1 = any length)
    horizon_multiple: int = 1

    def __init__(self, transition_dim: int, cond_dim: int | None) -> None:
        super().__init__()
        self.transition_dim = int(transition_dim)
        self.cond_dim = None if cond_dim is None else int(cond_dim)

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        cond_emb: torch.Tensor | None = None,
        cond_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError
