"""Pair sampling for the trajectory diffuser, as torchrl replay-buffer components.

* Preference augmentation (Eq. 5): :class:`BlockPairSampler` draws ``k`` uniformly over the
  ``K - 1`` adjacent block pairs, then ``tau0 ~ U(B_k)`` and ``tau1 ~ U(B_{k+1})``.
* Naive variant (Eq. 3, the ablation): only the labelled pairs, worse = condition, better =
  target, ties skipped (:func:`make_labeled_pair_buffer`).
* Unconditional (the SYNTHETIC baseline): uniformly drawn trajectories as ``"target"``, no
  condition (:func:`make_trajectory_buffer`).

Both buffers hold trajectories in a :class:`~torchrl.data.LazyTensorStorage` and return the
same pair batch: a TensorDict ``[B]`` with sub-TensorDicts ``"condition"`` (``tau0``) and
``"target"`` (``tau1``), each ``[B, H]``. The block buffer also sets ``"index"`` ``[B, 2]``
(dataset indices of condition/target) and ``"block"`` ``[B]`` (= ``k``, 0-based).
The samplers return index pairs ``[B, 2]``; :class:`PairToConditionTarget` (a replay-buffer
transform) turns the fetched ``[B, 2, H]`` data into the pair batch.

Example:
    >>> import torch
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=12, horizon=8, seed=0)
    >>> blocks = torch.arange(12) // 4  # 3 blocks of 4
    >>> rb = make_block_pair_buffer(trajs, blocks, batch_size=5, seed=0)
    >>> batch = rb.sample()
    >>> batch["condition"].batch_size, batch["target"].batch_size
    (torch.Size([5, 8]), torch.Size([5, 8]))
    >>> bool((blocks[batch["index"][:, 1]] == blocks[batch["index"][:, 0]] + 1).all())
    True
"""
from __future__ import annotations

from typing import Any, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage
from torchrl.envs.transforms import Transform

from torchrl_ftb.data.trajectories import validate_trajectories
from torchrl_ftb.preference.score import NORMALIZED_SCORE_KEY, with_normalized_scores

__all__ = [
    "BlockPairSampler",
    "PairToConditionTarget",
    "make_block_pair_buffer",
    "make_labeled_pair_buffer",
    "make_trajectory_buffer",
    "standardized_starts",
]


def standardized_starts(starts: torch.Tensor, *, reference: torch.Tensor | None = None) -> torch.Tensor:
    """``starts`` z-scored per dimension by ``reference``'s mean and std (default: ``starts``'); a dimension
    that does not vary in ``reference`` is only centred. The scale on which :class:`BlockPairSampler` calls
    starts near (and the benches measure how near).

    Example:
        >>> standardized_starts(torch.tensor([[0.0, 5.0], [2.0, 5.0]])).tolist()
        [[-0.7071067690849304, 0.0], [0.7071067690849304, 0.0]]
    """
    reference = starts if reference is None else reference
    std = reference.std(0)
    return (starts - reference.mean(0)) / torch.where(std > 1e-8, std, torch.ones_like(std))


def _transition_weights(weights: Sequence[float] | torch.Tensor | None, num_blocks: int,
                        num_transitions: int) -> torch.Tensor | None:
    """Transition weights (``num_transitions``: ``K - 1``, or ``K`` with the top block's own pairs last), checked
    and normalised to probabilities (``None`` stays ``None``)."""
    if weights is None:
        return None
    w = torch.as_tensor(weights, dtype=torch.float64).flatten()
    n, top = num_transitions, num_transitions == num_blocks
    if w.numel() != n or not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or float(w.sum()) <= 0:
        what = " and the top block's own pairs, last" if top else ""
        raise ValueError(f"BlockPairSampler: block_weights must be {n} finite non-negative weights "
                         f"(one per transition k -> k+1 of {num_blocks} blocks{what}), not all zero; got {w.tolist()}")
    return (w / w.sum()).float()


class BlockPairSampler(Sampler):
    """Samples index pairs ``(i0, i1)`` with ``i0 ~ U(B_k)``, ``i1 ~ U(B_{k+1})``, ``k ~ U{0..K-2}``.

    Uses the replay buffer's generator (``_rng``) when it has one, so a seeded buffer is
    reproducible. Works on a 1-D storage whose item ``i`` is trajectory ``i`` (e.g. a
    :class:`~torchrl.data.LazyTensorStorage` filled with an ``[N, H]`` batch).

    With ``neighbours=m`` (not the paper's), ``i1`` is drawn from the ``m`` members of ``B_{k+1}`` that
    start nearest to ``i0`` (Euclidean distance of the z-scored ``starts``, e.g. first observations:
    on Meta-World they hold the object's and the goal's positions). The pairs then teach "a better
    trajectory *from the same situation*" instead of "any better trajectory", which is what a flow
    step asks of a sample conditioned on one top-k trajectory.

    With ``block_weights`` (not the paper's), the transition ``k -> k+1`` is drawn with probability
    proportional to ``block_weights[k]`` instead of uniformly: e.g. ``[0, 0, 1, 1]`` with ``K = 5``
    teaches only the transitions into the two top blocks, the ones a flow from the top-k asks for.

    With ``top_block_scores`` (not the paper's), the top block also pairs with itself, as a ``K``-th
    transition drawn as often as each other one: ``i0`` is any member of ``B_K`` but its best and ``i1`` a
    member scored above it. Eq. 5 never shows the diffuser a top-block condition, yet the flow conditions on
    the top-k, which come from there; these pairs make that condition one the model was trained on, with
    "better than this" as its target (with ``neighbours``, one of the ``m`` better members that start nearest).

    Args:
        block_ids: ``int64 [N]`` block of each stored trajectory (from :func:`make_blocks`),
            contiguous ids ``0..K-1`` with ``K >= 2``, every block non-empty.

    Keyword Args:
        neighbours: ``m >= 1``: pair each ``i0`` only with its ``m`` nearest next-block trajectories
            (all of them when the block is smaller). ``None`` (default): uniform, Eq. 5.
        starts: ``[N, D]`` what "near" compares (needed with ``neighbours``).
        block_weights: ``K - 1`` non-negative weights of the transitions ``k -> k+1`` (not all zero;
            ``K`` with ``top_block_scores``, the top block's own pairs last). ``None`` (default): uniform, Eq. 5.
        top_block_scores: ``[N]`` scores that order the top block (e.g. ``s_psi``, the blocks' own); given,
            the sampler also draws pairs inside the top block (needs >= 2 members). ``None`` (default): Eq. 5.

    Returns (from :meth:`sample`):
        ``index`` ``[B, 2]`` and info ``{"block": k [B]}``.

    Example:
        >>> import torch
        >>> blocks = torch.tensor([0, 0, 1, 1])
        >>> starts = torch.tensor([[0.0], [10.0], [9.0], [1.0]])
        >>> sampler = BlockPairSampler(blocks, neighbours=1, starts=starts)
        >>> sampler.neighbour_table.tolist()  # 0 -> 3 (start 1), 1 -> 2 (start 9)
        [[3], [2], [-1], [-1]]
    """

    def __init__(self, block_ids: torch.Tensor, *, neighbours: int | None = None,
                 starts: torch.Tensor | None = None,
                 block_weights: Sequence[float] | torch.Tensor | None = None,
                 top_block_scores: torch.Tensor | None = None) -> None:
        block_ids = torch.as_tensor(block_ids)
        if block_ids.ndim != 1 or block_ids.dtype not in (torch.int64, torch.int32):
            raise ValueError(f"BlockPairSampler: block_ids must be a 1-D integer tensor, got {block_ids.dtype} {list(block_ids.shape)}")
        block_ids = block_ids.long().cpu()
        if block_ids.numel() == 0 or int(block_ids.min()) < 0:
            raise ValueError("BlockPairSampler: block_ids must be non-empty and >= 0")
        counts = torch.bincount(block_ids)
        if counts.numel() < 2:
            raise ValueError("BlockPairSampler: need at least 2 blocks to form adjacent pairs")
        if bool((counts == 0).any()):
            raise ValueError(f"BlockPairSampler: block ids must be contiguous; empty blocks {torch.nonzero(counts == 0).flatten().tolist()}")
        self.block_ids = block_ids
        self.num_blocks = int(counts.numel())
        self._counts = counts
        self._offsets = torch.cumsum(counts, 0) - counts
        self._members = torch.argsort(block_ids, stable=True)  # trajectories grouped by block
        self.top_block_scores = None
        if top_block_scores is not None:
            top_block_scores = torch.as_tensor(top_block_scores).detach().double().cpu()
            if top_block_scores.shape != block_ids.shape or not bool(torch.isfinite(top_block_scores).all()):
                raise ValueError(f"BlockPairSampler: top_block_scores must be finite [N={block_ids.numel()}], "
                                 f"got {list(top_block_scores.shape)}")
            if int(counts[-1]) < 2:
                raise ValueError("BlockPairSampler: top_block_scores needs a top block of >= 2 trajectories "
                                 f"(it has {int(counts[-1])})")
            self.top_block_scores = top_block_scores
            top = torch.nonzero(block_ids == self.num_blocks - 1).squeeze(-1)
            #: the top block's members, worst to best (its own pairs: condition rank r0 < target rank r1)
            self._top_sorted = top[torch.argsort(top_block_scores[top], stable=True)]
        self.block_weights = _transition_weights(block_weights, self.num_blocks, self.num_transitions)
        self.neighbours = None if neighbours is None else int(neighbours)
        self.starts = None
        if self.neighbours is not None:
            if self.neighbours < 1:
                raise ValueError(f"BlockPairSampler: neighbours must be >= 1 (or None), got {neighbours}")
            if starts is None:
                raise ValueError("BlockPairSampler: neighbours needs starts ([N, D], what 'near' compares)")
            starts = torch.as_tensor(starts, dtype=torch.float32).cpu()
            if starts.ndim == 1:  # one feature per trajectory
                starts = starts[:, None]
            if starts.ndim != 2 or starts.shape[0] != block_ids.numel() or not bool(torch.isfinite(starts).all()):
                raise ValueError(f"BlockPairSampler: starts must be finite [N={block_ids.numel()}, D], "
                                 f"got {list(starts.shape)}")
            self.starts = starts
        #: ``[N, m]`` the next-block neighbours of each trajectory (-1: none; top block, or padding); with
        #: ``top_block_scores`` a top-block member's are its nearest better members (none for the best)
        self.neighbour_table, self._neighbour_counts = self._neighbour_table()

    @property
    def top_pairs(self) -> bool:
        """Whether the top block also pairs with itself (``top_block_scores`` given)."""
        return self.top_block_scores is not None

    @property
    def num_transitions(self) -> int:
        """Kinds of pairs drawn: ``K - 1`` adjacent-block transitions, plus the top block's own pairs."""
        return self.num_blocks - 1 + int(self.top_pairs)

    def _neighbour_table(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        if self.neighbours is None:
            return None, None
        z = standardized_starts(self.starts)
        table = torch.full((self.block_ids.numel(), self.neighbours), -1, dtype=torch.long)
        for k in range(self.num_blocks - 1):
            rows = torch.nonzero(self.block_ids == k).squeeze(-1)
            nxt = torch.nonzero(self.block_ids == k + 1).squeeze(-1)
            m = min(self.neighbours, nxt.numel())
            nearest = torch.cdist(z[rows], z[nxt]).topk(m, dim=1, largest=False).indices  # [|B_k|, m]
            table[rows, :m] = nxt[nearest]
        if self.top_pairs:  # each top member's nearest better members
            ranked = self._top_sorted
            for r in range(ranked.numel() - 1):
                better = ranked[r + 1:]
                m = min(self.neighbours, better.numel())
                nearest = torch.cdist(z[ranked[r:r + 1]], z[better]).topk(m, dim=1, largest=False).indices[0]
                table[ranked[r], :m] = better[nearest]
        return table, (table >= 0).sum(1)

    def _draw(self, block: torch.Tensor) -> torch.Tensor:
        u = torch.rand(block.shape, generator=self._rng)
        offset = (u * self._counts[block]).long().clamp(max=self._counts[block] - 1)
        return self._members[self._offsets[block] + offset]

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) != self.block_ids.numel():
            raise ValueError(
                f"BlockPairSampler: storage holds {len(storage)} trajectories but block_ids has "
                f"{self.block_ids.numel()} entries"
            )
        if self.block_weights is None:
            k = torch.randint(0, self.num_transitions, (batch_size,), generator=self._rng)
        else:
            k = torch.multinomial(self.block_weights, batch_size, replacement=True, generator=self._rng)
        own = k == self.num_blocks - 1  # the top block's own pairs (only with top_block_scores)
        i0 = self._draw(k)
        if bool(own.any()):  # their condition: any top member but the best
            n = self._top_sorted.numel()
            r0 = (torch.rand(k.shape, generator=self._rng) * (n - 1)).long().clamp(max=n - 2)
            i0 = torch.where(own, self._top_sorted[r0], i0)
        if self.neighbour_table is None:
            i1 = self._draw((k + 1).clamp(max=self.num_blocks - 1))
            if bool(own.any()):  # their target: a member ranked above the condition
                r1 = r0 + 1 + (torch.rand(k.shape, generator=self._rng) * (n - 1 - r0)).long().clamp(max=n - 2 - r0)
                i1 = torch.where(own, self._top_sorted[r1], i1)
        else:
            u = torch.rand(k.shape, generator=self._rng)
            count = self._neighbour_counts[i0]
            i1 = self.neighbour_table[i0, (u * count).long().clamp(max=count - 1)]
        return torch.stack([i0, i1], -1), {"block": k}

    def _empty(self) -> None:
        pass

    def dumps(self, path) -> None:  # state is the constructor argument only
        pass

    def loads(self, path) -> None:
        pass

    def state_dict(self) -> dict[str, Any]:
        return {"block_ids": self.block_ids, "neighbours": self.neighbours, "starts": self.starts,
                "block_weights": self.block_weights, "top_block_scores": self.top_block_scores}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.__init__(state_dict["block_ids"], neighbours=state_dict.get("neighbours"),
                      starts=state_dict.get("starts"), block_weights=state_dict.get("block_weights"),
                      top_block_scores=state_dict.get("top_block_scores"))

    def __repr__(self) -> str:
        near = "" if self.neighbours is None else f", neighbours={self.neighbours}"
        if self.block_weights is not None:
            near += f", block_weights={[round(w, 4) for w in self.block_weights.tolist()]}"
        if self.top_pairs:
            near += ", top_block_pairs=True"
        return f"{type(self).__name__}(num_blocks={self.num_blocks}, sizes={self._counts.tolist()}{near})"


class _AsTarget(Transform):
    """Replay-buffer transform: fetched trajectories ``[B, H]`` -> ``[B]`` with ``"target"`` only."""

    def __init__(self) -> None:
        super().__init__(in_keys=[], out_keys=[])

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return TensorDict({"target": tensordict}, batch_size=tensordict.batch_size[:1], device=tensordict.device)

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict


class PairToConditionTarget(Transform):
    """Replay-buffer transform: fetched pairs ``[B, 2, H]`` -> ``[B]`` with ``condition``/``target``.

    Item ``[:, 0]`` (the worse trajectory) becomes ``"condition"``, item ``[:, 1]``
    (the better) ``"target"``.

    Args:
        keys: entries to keep in each sub-TensorDict (default: all).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.randn(4, 2, 6, 3)}, [4, 2, 6])
        >>> out = PairToConditionTarget()(td)
        >>> out["target", "observation"].shape
        torch.Size([4, 6, 3])
    """

    def __init__(self, *, keys: Sequence[NestedKey] | None = None) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.keys = None if keys is None else list(keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims < 2 or tensordict.batch_size[1] != 2:
            raise ValueError(f"PairToConditionTarget: expected a [B, 2, ...] batch, got {list(tensordict.batch_size)}")
        data = tensordict if self.keys is None else tensordict.select(*self.keys)
        return TensorDict(
            {"condition": data[:, 0], "target": data[:, 1]},
            batch_size=tensordict.batch_size[:1],
            device=tensordict.device,
        )

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict


def _pair_buffer(data: TensorDictBase, sampler: Sampler, *, batch_size: int, seed: int | None,
                 keys: Sequence[NestedKey] | None, transform: Transform | None = None) -> TensorDictReplayBuffer:
    """Storage of ``data`` (``keys`` only), ``sampler``, seeded generator, then ``transform``
    (default :class:`PairToConditionTarget`)."""
    if batch_size < 1:
        raise ValueError(f"pair buffer: batch_size must be >= 1, got {batch_size}")
    if keys is not None:  # store only what the pairs carry (no copy of unused dataset keys)
        missing = [k for k in keys if k not in data.keys(True)]
        if missing:
            raise ValueError(f"pair buffer: the trajectories have no {missing} (has {sorted(map(str, data.keys(True, True)))})")
        data = data.select(*keys)
    rb = TensorDictReplayBuffer(
        storage=LazyTensorStorage(data.batch_size[0], ndim=1, device=data.device or "cpu"),
        sampler=sampler,
        batch_size=batch_size,
        generator=None if seed is None else torch.Generator().manual_seed(int(seed)),
    )
    rb.extend(data)
    rb.append_transform(PairToConditionTarget() if transform is None else transform)
    return rb


def make_block_pair_buffer(
    trajs: TensorDictBase,
    block_ids: torch.Tensor,
    *,
    batch_size: int,
    seed: int | None = None,
    keys: Sequence[NestedKey] | None = ("observation", "action", "mask"),
    scores: torch.Tensor | None = None,
    neighbours: int | None = None,
    block_weights: Sequence[float] | torch.Tensor | None = None,
    top_block_scores: torch.Tensor | None = None,
) -> TensorDictReplayBuffer:
    """Replay buffer over ``trajs`` whose ``sample()`` is an adjacent-block pair batch (Eq. 5).

    Args:
        trajs: ``[N, H]`` trajectory batch.
        block_ids: ``[N]`` block ids (:func:`make_blocks`).

    Keyword Args:
        batch_size: pairs per ``sample()``.
        seed: seeds the buffer's generator (``None``: global RNG).
        keys: entries kept in ``condition``/``target`` (``None``: all); e.g. add
            ``("next", "reward")`` when the reward is diffused too.
        scores: ``[N]`` scores ``s_psi`` of ``trajs`` (the blocks'); when given, every pair also
            carries each trajectory's dataset-normalised score under :data:`NORMALIZED_SCORE_KEY`
            (:func:`with_normalized_scores`): what a ``score_condition`` diffuser reads. The flow
            normalises with the same dataset minimum and maximum.
        neighbours: pair each condition only with the ``m`` next-block trajectories whose first
            observation is nearest to its own (:class:`BlockPairSampler`; not the paper's).
            ``None`` (default): uniform pairs.
        block_weights: ``K - 1`` weights of the transitions ``k -> k+1`` (:class:`BlockPairSampler`; not the
            paper's). ``None`` (default): every transition equally often.
        top_block_scores: ``[N]`` scores ordering the top block (usually the blocks' ``scores``): also draw
            pairs inside the top block, condition below target (:class:`BlockPairSampler`; not the paper's).

    Raises:
        ValueError: malformed ``trajs``, ``block_ids`` or ``scores`` of the wrong length, < 2 blocks,
            ``block_weights`` not one non-negative weight per transition, a top block of one trajectory.
    """
    validate_trajectories(trajs, name="make_block_pair_buffer: trajs")
    block_ids = torch.as_tensor(block_ids)
    if block_ids.shape != trajs.batch_size[:1]:
        raise ValueError(
            f"make_block_pair_buffer: block_ids has shape {list(block_ids.shape)}, expected [{trajs.batch_size[0]}]"
        )
    if scores is not None:
        trajs = with_normalized_scores(trajs, scores)
        keys = None if keys is None else [*keys, NORMALIZED_SCORE_KEY]
    starts = None if neighbours is None else trajs.get("observation")[:, 0]
    sampler = BlockPairSampler(block_ids, neighbours=neighbours, starts=starts, block_weights=block_weights,
                               top_block_scores=top_block_scores)
    return _pair_buffer(trajs, sampler, batch_size=batch_size, seed=seed, keys=keys)


def make_labeled_pair_buffer(
    labels: TensorDictBase,
    *,
    batch_size: int,
    seed: int | None = None,
    keys: Sequence[NestedKey] | None = ("observation", "action", "mask"),
) -> TensorDictReplayBuffer:
    """Replay buffer of the labelled pairs only (naive Eq. 3): worse -> condition, better -> target.

    Pairs with label 0.5 (ties) are skipped; label 1 keeps ``(tau0, tau1)``, label 0 swaps
    them. Sampling is uniform with replacement; the batch format matches
    :func:`make_block_pair_buffer` except ``"index"``, which is ``[B]`` here (the index of
    the stored non-tie pair) and there is no ``"block"``.

    Raises:
        ValueError: missing keys, labels outside {0, 0.5, 1}, or no non-tie pair.
    """
    for key in ("tau0", "tau1", "label"):
        if key not in labels.keys():
            raise ValueError(f"make_labeled_pair_buffer: labels miss {key!r}")
    label = labels.get("label")
    if not bool(((label == 0) | (label == 0.5) | (label == 1)).all()):
        raise ValueError("make_labeled_pair_buffer: 'label' must be in {0, 0.5, 1}")
    decided = label != 0.5
    if not bool(decided.any()):
        raise ValueError("make_labeled_pair_buffer: all labels are ties; no pair to learn from")
    tau0, tau1 = labels.get("tau0")[decided], labels.get("tau1")[decided]
    swap = (label[decided] == 0)
    worse = torch.where(_expand(swap, tau0), tau1, tau0)
    better = torch.where(_expand(swap, tau0), tau0, tau1)
    pairs = torch.stack([worse, better], 1)  # [M', 2, L]
    return _pair_buffer(pairs, RandomSampler(), batch_size=batch_size, seed=seed, keys=keys)


def _expand(flag: torch.Tensor, like: TensorDictBase) -> torch.Tensor:
    return flag.reshape(-1, *([1] * (like.batch_dims - 1)))


def make_trajectory_buffer(
    trajs: TensorDictBase,
    *,
    batch_size: int,
    seed: int | None = None,
    keys: Sequence[NestedKey] | None = ("observation", "action", "mask"),
) -> TensorDictReplayBuffer:
    """Replay buffer of uniformly drawn trajectories as ``"target"`` (no condition).

    What an unconditional diffuser (``make_diffuser(..., unconditional=True)``, the SYNTHETIC
    baseline) trains on; the batch is a TensorDict ``[B]`` with the sub-TensorDict
    ``"target"`` ``[B, H]`` (and the buffer's ``"index"``).

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> rb = make_trajectory_buffer(make_toy_dataset(num_trajectories=6, horizon=4), batch_size=3, seed=0)
        >>> rb.sample()["target"].batch_size
        torch.Size([3, 4])
    """
    validate_trajectories(trajs, name="make_trajectory_buffer: trajs")
    return _pair_buffer(trajs, RandomSampler(), batch_size=batch_size, seed=seed, keys=keys, transform=_AsTarget())
