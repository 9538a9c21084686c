"""Condition-trajectory encoder ``e_theta`` (FTB §3.1) with a learned null condition for CFG.

A 1-D convolutional network maps a normalised condition trajectory ``[B, Hc, D]`` to an
embedding ``zeta [B, Hc, d_tau]`` (two Conv1d + GroupNorm + Mish blocks, as in the authors'
code). Padded condition steps are zeroed at the input and excluded from attention through
the returned key-padding mask (``True`` = valid). The *null* condition used for
classifier-free guidance is one learned token: ``[B, 1, d_tau]`` with mask ``[B, 1]`` True.

``score_condition=True`` adds the condition's own score as a feature: an MLP of its
dataset-normalised score ``ŝ(tau_0)`` (the flow filter's scale, dataset in [0, 1]) is added to
every step's embedding, so it reaches every condition path of the backbone (cross-attention
values, the pooled global vector, the concatenated input). ``ŝ`` is a function of ``tau_0``
through the frozen score model, so the diffuser still models ``p(tau_1 | tau_0)`` (Eq. 5);
the feature hands the encoder the one global property FTB's pairs tie a target to (its
condition's block), which a small convolutional encoder did not learn to compute from 500
steps (BENCHMARKS, "Does the diffuser follow its condition?"). Decision Diffuser conditions
on returns the same way. The null condition carries no score.

``linear_skip=True`` adds a pointwise linear map of the (masked, normalised) condition to the
embedding, beside the convolutional path (written here: no encoder we could reuse has it). Each
convolutional block ends in a GroupNorm over the whole horizon, which removes every trajectory's
own level and scale per channel group, so what is constant along a trajectory (an object's or
goal's position) and how far a channel moves reach the backbone only in part; the skip hands them
on unnormalised. Measured on Meta-World's copy task it changed little: what kept the condition out
of the samples was the epsilon loss at high noise (BENCHMARKS, "v prediction").

``masked_norm=True`` makes the embedding of a condition's valid steps independent of the padding
after them (off by default: the authors' encoder, and every trained ``cpu``/``paper`` model so far).
By default padded steps are zeroed at the input only: after the first convolution they hold its bias,
each GroupNorm takes its statistics over the whole horizon, padding included, and the second
convolution mixes padded features into the last valid steps, so a short trajectory padded to 500
steps (a fast Meta-World success) is normalised mostly by its padding. With ``masked_norm`` each
GroupNorm's statistics are over the valid steps only and every block's output is zeroed on padded
steps (:class:`MaskedGroupNorm`).

Example:
    >>> import torch
    >>> enc = TrajectoryEncoder(5, embed_dim=16)
    >>> emb, mask = enc(torch.randn(2, 9, 5), torch.ones(2, 9, dtype=torch.bool))
    >>> emb.shape, mask.shape
    (torch.Size([2, 9, 16]), torch.Size([2, 9]))
    >>> enc.null(2, 9)[0].shape
    torch.Size([2, 9, 16])
    >>> TrajectoryEncoder(5, embed_dim=16, linear_skip=True)(torch.randn(2, 9, 5), torch.ones(2, 9).bool())[0].shape
    torch.Size([2, 9, 16])
    >>> scored = TrajectoryEncoder(5, embed_dim=16, score_condition=True)
    >>> scored(torch.randn(2, 9, 5), torch.ones(2, 9, dtype=torch.bool), score=torch.tensor([0.2, 0.9]))[0].shape
    torch.Size([2, 9, 16])
"""
from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["MaskedGroupNorm", "TrajectoryEncoder"]


class MaskedGroupNorm(nn.GroupNorm):
    """``nn.GroupNorm`` over ``[B, C, H]`` whose statistics are taken over the valid steps of ``mask [B, H]`` only
    (written here: torch's GroupNorm takes no mask). A row without valid steps is left at its affine bias.

    Example:
        >>> norm = MaskedGroupNorm(2, 4)
        >>> x, mask = torch.randn(1, 4, 6), torch.tensor([[True] * 4 + [False] * 2])
        >>> padded = torch.cat([x[..., :4], torch.full((1, 4, 2), 50.0)], -1)
        >>> torch.allclose(norm(x, mask)[..., :4], norm(padded, mask)[..., :4])
        True
    """

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        b, c, h = x.shape
        g = self.num_groups
        m = mask[:, None, None, :].to(x.dtype)  # [B, 1, 1, H]
        xg = x.reshape(b, g, c // g, h)
        count = (m.sum(-1, keepdim=True) * (c // g)).clamp_min(1.0)
        mean = (xg * m).sum((-1, -2), keepdim=True) / count
        var = (((xg - mean) * m) ** 2).sum((-1, -2), keepdim=True) / count
        y = ((xg - mean) * torch.rsqrt(var + self.eps)).reshape(b, c, h)
        return y * self.weight[None, :, None] + self.bias[None, :, None]


class TrajectoryEncoder(nn.Module):
    """Conv1d trajectory encoder ``transition_dim -> embed_dim`` + learned null token.

    Args:
        transition_dim: per-step size of the (normalised) condition.
        embed_dim: output size ``d_tau``.
        kernel_size: temporal kernel of both convolutions.
        score_condition: also embed the condition's normalised score (``forward(score=)``).
        linear_skip: add a pointwise linear map of the condition itself to the embedding (what
            the convolutional path's GroupNorm takes out: each trajectory's level and scale).
        masked_norm: normalise over the valid steps only and zero padded steps after each block (module
            docstring); another module layout, so a model trained without it does not load with it.
    """

    def __init__(self, transition_dim: int, *, embed_dim: int = 128, kernel_size: int = 5,
                 score_condition: bool = False, linear_skip: bool = False, masked_norm: bool = False) -> None:
        super().__init__()
        self.transition_dim = int(transition_dim)
        self.embed_dim = int(embed_dim)
        self.score_condition = bool(score_condition)
        if self.score_condition:
            self.score_mlp = nn.Sequential(nn.Linear(1, embed_dim), nn.Mish(), nn.Linear(embed_dim, embed_dim))
        groups = math.gcd(8, self.embed_dim)
        self.masked_norm = bool(masked_norm)
        if self.masked_norm:
            self.convs = nn.ModuleList([nn.Conv1d(transition_dim, embed_dim, kernel_size, padding=kernel_size // 2),
                                        nn.Conv1d(embed_dim, embed_dim, kernel_size, padding=kernel_size // 2)])
            self.norms = nn.ModuleList([MaskedGroupNorm(groups, embed_dim) for _ in range(2)])
        else:
            self.net = nn.Sequential(
                nn.Conv1d(transition_dim, embed_dim, kernel_size, padding=kernel_size // 2),
                nn.GroupNorm(groups, embed_dim),
                nn.Mish(),
                nn.Conv1d(embed_dim, embed_dim, kernel_size, padding=kernel_size // 2),
                nn.GroupNorm(groups, embed_dim),
                nn.Mish(),
            )
        self.linear_skip = bool(linear_skip)
        if self.linear_skip:
            self.skip = nn.Conv1d(transition_dim, embed_dim, 1)
        self.null_embedding = nn.Parameter(torch.randn(embed_dim) * 0.02)

    def forward(self, x: torch.Tensor, mask: torch.Tensor,
                score: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Encode ``x [B, Hc, D]`` (padded steps are zeroed here); returns ``(emb, mask)``.

        ``score [B]`` (the normalised condition score) is required with ``score_condition``
        and must be ``None`` without it.
        """
        if x.ndim != 3 or x.shape[-1] != self.transition_dim:
            raise ValueError(f"TrajectoryEncoder: condition must be [B, Hc, {self.transition_dim}], got {list(x.shape)}")
        if self.score_condition != (score is not None):
            raise ValueError("TrajectoryEncoder: pass score= exactly when built with score_condition=True "
                             f"(score_condition={self.score_condition})")
        mask = mask.bool()
        x = x * mask[..., None].to(x.dtype)
        h = x.transpose(1, 2)
        emb = self._conv_path(h, mask)
        emb = (emb + self.skip(h) if self.linear_skip else emb).transpose(1, 2)
        if score is not None:
            if score.shape != x.shape[:1]:
                raise ValueError(f"TrajectoryEncoder: score must be [{x.shape[0]}], got {list(score.shape)}")
            emb = emb + self.score_mlp(score[:, None].to(emb.dtype))[:, None, :]
        return emb, mask

    def _conv_path(self, h: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The two Conv1d + GroupNorm + Mish blocks on ``h [B, D, Hc]``."""
        if not self.masked_norm:
            return self.net(h)
        valid = mask[:, None, :].to(h.dtype)
        for conv, norm in zip(self.convs, self.norms):
            h = nn.functional.mish(norm(conv(h), mask)) * valid
        return h

    def null(self, batch: int, length: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The null condition shaped like an encoded one: token at step 0, the rest masked out."""
        emb = torch.zeros(batch, length, self.embed_dim, device=self.null_embedding.device,
                          dtype=self.null_embedding.dtype)
        emb[:, 0] = self.null_embedding
        mask = torch.zeros(batch, length, dtype=torch.bool, device=emb.device)
        mask[:, 0] = True
        return emb, mask

    def drop(self, emb: torch.Tensor, mask: torch.Tensor, drop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Replace the conditions where ``drop [B]`` is True by the null condition (CFG training)."""
        null_emb, null_mask = self.null(emb.shape[0], emb.shape[1])
        return (torch.where(drop[:, None, None], null_emb.to(emb.dtype), emb),
                torch.where(drop[:, None], null_mask, mask))
