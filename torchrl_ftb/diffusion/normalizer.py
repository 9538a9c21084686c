"""Per-dimension z-score of trajectory steps, fitted on valid (non-padded) steps only.

The statistics are buffers, so they travel with ``state_dict`` / ``.to(device)`` and are
saved in every checkpoint. (The authors fitted them after zero-padding, which skews them.)

Example:
    >>> import torch
    >>> norm = TrajectoryNormalizer(2)
    >>> x = torch.tensor([[[1.0, 10.0], [3.0, 30.0], [0.0, 0.0]]])
    >>> mask = torch.tensor([[True, True, False]])
    >>> _ = norm.fit(x, mask)
    >>> norm.mean.tolist()
    [2.0, 20.0]
    >>> torch.allclose(norm.unnormalize(norm.normalize(x)), x, atol=1e-5)
    True
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["TrajectoryNormalizer"]


class TrajectoryNormalizer(nn.Module):
    """``(x - mean) / std`` per last dimension, statistics from valid steps only.

    Args:
        dim: size of the last dimension.
        min_std: floor on the std (constant dimensions map to 0 instead of blowing up).
    """

    def __init__(self, dim: int, *, min_std: float = 1e-3) -> None:
        super().__init__()
        self.dim = int(dim)
        self.min_std = float(min_std)
        self.register_buffer("mean", torch.zeros(self.dim))
        self.register_buffer("std", torch.ones(self.dim))
        # raw-unit range of the fitted data (bounds for clipping denoised samples)
        self.register_buffer("low", torch.full((self.dim,), -float("inf")))
        self.register_buffer("high", torch.full((self.dim,), float("inf")))
        # 1.0 where the fitted data are constant (std below min_std): candidates for static dims
        self.register_buffer("constant", torch.zeros(self.dim))
        # float flag (not bool) so it survives any float-only state handling; 1.0 once fitted
        self.register_buffer("fitted", torch.zeros(()))

    @property
    def is_fitted(self) -> bool:
        """Whether :meth:`fit` has been called (or fitted statistics were loaded)."""
        return bool(self.fitted > 0)

    @torch.no_grad()
    def fit(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> "TrajectoryNormalizer":
        """Fit mean/std on ``x [..., dim]`` over the entries where ``mask [...]`` is True."""
        if x.shape[-1] != self.dim:
            raise ValueError(f"TrajectoryNormalizer.fit: last dimension {x.shape[-1]} != {self.dim}")
        values = x.reshape(-1, self.dim) if mask is None else x[mask.bool()]
        if values.shape[0] < 2:
            raise ValueError(f"TrajectoryNormalizer.fit: need at least 2 valid steps, got {values.shape[0]}")
        if not bool(torch.isfinite(values).all()):
            raise ValueError("TrajectoryNormalizer.fit: non-finite values on valid steps")
        values = values.double()
        self.mean.copy_(values.mean(0))
        std = values.std(0)
        self.constant.copy_((std < self.min_std).to(self.constant.dtype))
        self.std.copy_(std.clamp(min=self.min_std))
        self.low.copy_(values.min(0).values)
        self.high.copy_(values.max(0).values)
        self.fitted.fill_(1.0)
        return self

    def constant_dims(self) -> list[int]:
        """Indices of the dimensions that were constant in the fitted data."""
        return [int(i) for i in torch.nonzero(self.constant > 0).flatten()]

    def normalized_bounds(self, margin: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Data range in z-score space, widened by ``margin`` x its width on both sides."""
        low, high = self.normalize(self.low), self.normalize(self.high)
        width = high - low
        return low - margin * width, high + margin * width

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Map raw values to z-scores."""
        return (x - self.mean) / self.std

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        """Map z-scores back to raw values."""
        return x * self.std + self.mean
