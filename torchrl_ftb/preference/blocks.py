"""Cluster trajectories into K ascending score blocks ``B_1 < ... < B_K`` (Alg. 2, line 7).

scikit-learn :class:`~sklearn.cluster.KMeans` on the 1-D scores; clusters are renumbered
0..K-1 by ascending centre. In 1-D, nearest-centre assignment makes every block an interval
of the sorted scores.

Degenerate cases (each warns with :class:`BlockWarning` and falls back as documented):

* fewer distinct scores than ``num_blocks`` -> K is reduced to the number of distinct scores;
* blocks smaller than ``min_block_size`` (e.g. one outlier trajectory alone at the top) are
  merged into their nearer neighbouring block (by the gap between the blocks' edge scores),
  repeatedly, so the final K may be smaller; ids stay contiguous and ascending.

``num_blocks > N`` or ``num_blocks < 1`` raises :class:`ValueError`.

Example:
    >>> import torch
    >>> make_blocks(torch.tensor([0.0, 0.1, 5.0, 5.2, 9.9, 10.0]), 3, seed=0).tolist()
    [0, 0, 1, 1, 2, 2]
"""
from __future__ import annotations

import warnings

import numpy as np
import torch
from sklearn.cluster import KMeans

__all__ = ["make_blocks", "BlockWarning"]


class BlockWarning(UserWarning):
    """A degenerate block configuration was repaired (fewer blocks than asked)."""


def _merge_small_blocks(ids: np.ndarray, values: np.ndarray, min_size: int) -> np.ndarray:
    """Merge blocks below ``min_size`` into the nearer neighbour; ``ids`` contiguous, ascending."""
    while True:
        k = int(ids.max()) + 1
        sizes = np.bincount(ids, minlength=k)
        small = np.flatnonzero(sizes < min_size)
        if k == 1 or small.size == 0:
            return ids
        b = int(small[np.argmin(sizes[small])])  # smallest first (deterministic: lowest id on ties)
        lo, hi = values[ids == b].min(), values[ids == b].max()
        gap_down = lo - values[ids == b - 1].max() if b > 0 else np.inf
        gap_up = values[ids == b + 1].min() - hi if b < k - 1 else np.inf
        target = b - 1 if gap_down <= gap_up else b + 1
        ids = np.where(ids == b, target, ids)
        ids = np.where(ids > b, ids - 1, ids)  # keep ids contiguous


def make_blocks(
    scores: torch.Tensor,
    num_blocks: int,
    *,
    seed: int = 0,
    n_init: int = 10,
    min_block_size: int = 2,
) -> torch.Tensor:
    """Block id of each trajectory, ``int64 [N]`` in ``0..K'-1`` ascending by score.

    Args:
        scores: ``[N]`` trajectory scores (e.g. from :func:`score_trajectories`).
        num_blocks: requested K (paper: 20 on D4RL, 5 on Meta-World).

    Keyword Args:
        seed: KMeans ``random_state`` (same inputs + seed -> same blocks).
        n_init: KMeans restarts.
        min_block_size: smaller blocks are merged into a neighbour (1 disables merging).

    Returns:
        Block ids on ``scores``' device; ``K' = ids.max() + 1 <= num_blocks``.

    Raises:
        ValueError: ``scores`` not 1-D / non-finite / empty, ``num_blocks`` < 1 or > N.

    Example:
        >>> import torch
        >>> ids = make_blocks(torch.arange(10.0), 2, seed=0)
        >>> ids.tolist()
        [0, 0, 0, 0, 0, 1, 1, 1, 1, 1]
    """
    if not isinstance(scores, torch.Tensor) or scores.ndim != 1 or scores.numel() == 0:
        raise ValueError(f"make_blocks: scores must be a non-empty 1-D tensor, got {getattr(scores, 'shape', type(scores))}")
    if not bool(torch.isfinite(scores).all()):
        raise ValueError("make_blocks: scores contain NaN or inf")
    n = scores.numel()
    if num_blocks < 1 or num_blocks > n:
        raise ValueError(f"make_blocks: num_blocks must be in [1, N={n}], got {num_blocks}")
    if min_block_size < 1:
        raise ValueError(f"make_blocks: min_block_size must be >= 1, got {min_block_size}")
    values = scores.detach().double().cpu().numpy()
    distinct = np.unique(values).size
    k = num_blocks
    if distinct < k:
        warnings.warn(
            f"make_blocks: only {distinct} distinct scores for {num_blocks} blocks; using K={distinct}",
            BlockWarning, stacklevel=2,
        )
        k = distinct
    if k == 1:
        return torch.zeros(n, dtype=torch.long, device=scores.device)
    km = KMeans(n_clusters=k, n_init=n_init, random_state=seed).fit(values[:, None])
    order = np.argsort(km.cluster_centers_[:, 0], kind="stable")
    rank = np.empty(k, dtype=np.int64)
    rank[order] = np.arange(k)
    ids = rank[km.labels_]
    # KMeans can leave a cluster empty only in pathological cases; drop gaps to stay contiguous
    ids = np.unique(ids, return_inverse=True)[1].astype(np.int64)
    merged = _merge_small_blocks(ids, values, min_block_size)
    kept = int(merged.max()) + 1
    if kept < k:
        warnings.warn(
            f"make_blocks: {num_blocks} blocks requested, {kept} kept (blocks smaller than "
            f"{min_block_size} trajectories merged into their nearer neighbour)",
            BlockWarning, stacklevel=2,
        )
    return torch.as_tensor(merged, dtype=torch.long, device=scores.device)
