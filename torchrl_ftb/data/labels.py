"""Preference labels: scripted teachers, label sets, the PT/IPL file format, persistence.

A label set is a :class:`~tensordict.TensorDict` with ``batch_size=[M]`` (see
``docs/conventions.md``):

* ``"tau0"``, ``"tau1"``: ``[M, L]`` trajectory batches (``observation``, ``action``,
  ``mask``, and every other key of the dataset they were cut from, e.g.
  ``("next", "reward")``);
* ``"label"``: ``[M]`` float32 in {0, 0.5, 1}; **1 means ``tau1`` is preferred**;
* optional ``"index0"``, ``"index1"`` (``[M]`` int64 dataset trajectory indices) and
  ``"start0"``, ``"start1"`` (``[M]`` int64 first step of the segment, 0 for full trajectories);
* ``"teacher"``: a non-tensor string naming who labelled the pairs (e.g. ``"return"``,
  ``"success(discount=0.99)"``, ``"pt-file:num100_human_train"``). Every result must say
  which teacher it used: on Meta-World v3 return and success disagree
  (``shared/notes/datasets.md``).

Scripted teachers compare true returns, as in the paper: ``y = argmax_i sum_h r(s_h^i, a_h^i)``
(undiscounted by default, ties within ``tie_tol`` give 0.5). :class:`SuccessTeacher` first
prefers a trajectory that ever succeeds over one that never does.

Full Meta-World trajectories with the stop rule (an episode ends 25 steps after success)
make a *slow* success earn more than a fast one. ``horizon=`` (in :func:`true_return` and
both teachers) fixes this: a trajectory cut short without termination keeps earning its
last reward until ``horizon`` steps, so a faster success earns more. It is off by
default (the paper's plain sum) and only meaningful on full trajectories.

Example:
    >>> from torchrl_ftb.data.labels import ReturnTeacher, make_scripted_labels
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=16, horizon=8, seed=0)
    >>> labels = make_scripted_labels(trajs, num_pairs=5, teacher=ReturnTeacher(), seed=0)
    >>> labels.batch_size, labels["teacher"]
    (torch.Size([5]), 'return')
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from torchrl_ftb.data.trajectories import (
    NPZ_READ_ERRORS,
    atomic_directory,
    atomic_write_text,
    read_memmap_folder,
    stop_rule_fill,
    validate_trajectories,
)

__all__ = [
    "LABELS_FORMAT_VERSION",
    "METAWORLD_NUM_LABELS",
    "LOCOMOTION_NUM_LABELS",
    "true_return",
    "ReturnTeacher",
    "SuccessTeacher",
    "TEACHERS",
    "make_teacher",
    "make_scripted_labels",
    "draw_pairs",
    "label_pairs",
    "validate_labels",
    "check_labels_match",
    "load_pt_labels",
    "save_labels",
    "load_labels",
]

LABELS_FORMAT_VERSION = 1
#: Number of scripted labels the paper uses on Meta-World (full trajectories).
METAWORLD_NUM_LABELS = 30
#: Number of scripted labels the paper uses on D4RL locomotion (full trajectories).
LOCOMOTION_NUM_LABELS = 15
_LABEL_VALUES = (0.0, 0.5, 1.0)


# --------------------------------------------------------------------------- returns
def true_return(
    trajs: TensorDictBase,
    *,
    discount: float = 1.0,
    horizon: int | None = None,
    reward_key: NestedKey = ("next", "reward"),
) -> torch.Tensor:
    """Masked, discounted sum of the true reward of each trajectory: ``sum_h gamma^h r_h mask_h``.

    Args:
        trajs: ``[N, H]`` trajectory batch (full trajectories or segments) with ``reward_key``.
        discount: ``gamma`` in (0, 1]; 1.0 (default) is the paper's undiscounted sum.
        horizon: if given, a trajectory of length ``n < horizon`` whose last valid step is not
            ``("next", "terminated")`` keeps earning its last reward until step ``horizon - 1``
            (stop-rule episodes; see the module docstring). Needs ``("next", "terminated")``.
        reward_key: where the reward lives.

    Returns:
        ``float32 [N]`` returns (computed in float64).

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=3, horizon=4, seed=0)
        >>> true_return(trajs).shape
        torch.Size([3])
    """
    if not 0.0 < discount <= 1.0:
        raise ValueError(f"true_return: discount must be in (0, 1], got {discount}")
    keys = set(trajs.keys(include_nested=True, leaves_only=True))
    if reward_key not in keys:
        raise ValueError(
            f"true_return: trajectories have no {reward_key!r} (reward-free data cannot be scored "
            "by a scripted teacher)"
        )
    mask = trajs.get("mask")
    reward = trajs.get(reward_key).reshape(mask.shape).double() * mask
    steps = mask.shape[-1]
    weights = discount ** torch.arange(steps, dtype=torch.float64, device=reward.device)
    ret = (reward * weights).sum(-1)
    if horizon is not None:
        if horizon < 1:
            raise ValueError(f"true_return: horizon must be >= 1, got {horizon}")
        if ("next", "terminated") not in keys:
            raise ValueError(
                "true_return: horizon= needs ('next', 'terminated') to tell stop rules from "
                "terminations"
            )
        last, fill = stop_rule_fill(
            mask, horizon=horizon, discount=discount, terminated=trajs.get(("next", "terminated"))
        )
        ret = ret + fill * reward.gather(-1, last[:, None]).squeeze(-1)
    return ret.float()


# --------------------------------------------------------------------------- teachers
def _compare(score0: torch.Tensor, score1: torch.Tensor, tie_tol: float) -> torch.Tensor:
    # 1 where tau1 scores higher, 0 where tau0 does, 0.5 within tie_tol
    diff = score1.double() - score0.double()
    label = torch.where(diff > 0, 1.0, 0.0).to(torch.float32)
    return torch.where(diff.abs() <= tie_tol, torch.full_like(label, 0.5), label)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ReturnTeacher:
    """The paper's scripted teacher: prefer the trajectory (or segment) with the larger true return.

    Args:
        discount: ``gamma`` of :func:`true_return`; default 1.0, the paper's undiscounted sum.
        tie_tol: absolute return difference at or below which the label is 0.5 (default 0:
            exact ties only).
        horizon: stop-rule fill of :func:`true_return` (full trajectories only; default off).
        reward_key: where the true reward lives.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=4, horizon=8, seed=0)
        >>> labels = ReturnTeacher()(trajs[:2], trajs[2:])
        >>> bool((labels == (true_return(trajs[2:]) > true_return(trajs[:2])).float()).all())
        True
        >>> ReturnTeacher(discount=0.99).name
        'return(discount=0.99)'
    """

    discount: float = 1.0
    tie_tol: float = 0.0
    horizon: int | None = None
    reward_key: NestedKey = ("next", "reward")
    base_name: ClassVar[str] = "return"

    def __post_init__(self) -> None:
        if not 0.0 < self.discount <= 1.0:
            raise ValueError(
                f"{type(self).__name__}: discount must be in (0, 1], got {self.discount}"
            )
        if self.tie_tol < 0:
            raise ValueError(f"{type(self).__name__}: tie_tol must be >= 0, got {self.tie_tol}")
        if self.horizon is not None and self.horizon < 1:
            raise ValueError(f"{type(self).__name__}: horizon must be >= 1, got {self.horizon}")

    @property
    def name(self) -> str:
        """Short name plus the options that differ from the defaults: ``return(discount=0.99)``."""
        changed = [
            f"{f.name}={getattr(self, f.name)}"
            for f in dataclasses.fields(self)
            if getattr(self, f.name) != f.default
        ]
        return f"{self.base_name}({', '.join(changed)})" if changed else self.base_name

    def config(self) -> dict:
        """JSON-serialisable description (name and all options), to store beside labels."""
        cfg = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        cfg["reward_key"] = (
            list(cfg["reward_key"]) if isinstance(cfg["reward_key"], tuple) else cfg["reward_key"]
        )
        return {"name": self.name, "kind": self.base_name, **cfg}

    def returns(self, trajs: TensorDictBase) -> torch.Tensor:
        """True return of each trajectory under this teacher's definition (``[N]``)."""
        return true_return(
            trajs, discount=self.discount, horizon=self.horizon, reward_key=self.reward_key
        )

    def __call__(self, tau0: TensorDictBase, tau1: TensorDictBase) -> torch.Tensor:
        """Labels ``[M]`` in {0, 0.5, 1} for pairs ``(tau0[m], tau1[m])``; 1: ``tau1`` preferred."""
        return _compare(self.returns(tau0), self.returns(tau1), self.tie_tol)


@dataclasses.dataclass(frozen=True, kw_only=True)
class SuccessTeacher(ReturnTeacher):
    """Success-aware teacher: a trajectory that ever succeeds beats one that never does.

    When both or neither succeed, it falls back to :class:`ReturnTeacher` with the same
    options. Success is ``any(("next", "success") & mask)`` over the trajectory or segment.

    Args:
        success_key: where the per-step success flag lives.
        (others as :class:`ReturnTeacher`)

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=4, horizon=8, seed=0)
        >>> SuccessTeacher()(trajs[:2], trajs[2:]).shape
        torch.Size([2])
    """

    success_key: NestedKey = ("next", "success")
    base_name: ClassVar[str] = "success"

    def succeeded(self, trajs: TensorDictBase) -> torch.Tensor:
        """``bool [N]``: whether each trajectory ever succeeds on a valid step."""
        if self.success_key not in trajs.keys(include_nested=True, leaves_only=True):
            raise ValueError(f"{self.name} teacher: trajectories have no {self.success_key!r} flag")
        mask = trajs.get("mask")
        return (trajs.get(self.success_key).reshape(mask.shape).bool() & mask).any(-1)

    def config(self) -> dict:
        cfg = super().config()
        cfg["success_key"] = (
            list(self.success_key) if isinstance(self.success_key, tuple) else self.success_key
        )
        return cfg

    def __call__(self, tau0: TensorDictBase, tau1: TensorDictBase) -> torch.Tensor:
        s0, s1 = self.succeeded(tau0), self.succeeded(tau1)
        by_return = super().__call__(tau0, tau1)
        return torch.where(s0 == s1, by_return, s1.to(torch.float32))


#: Registry of scripted teachers by name (see :func:`make_teacher`).
TEACHERS: dict = {"return": ReturnTeacher, "success": SuccessTeacher}


def make_teacher(name: str, **kwargs: Any) -> ReturnTeacher:
    """Build a scripted teacher by name: ``"return"`` (the paper's) or ``"success"``.

    Example:
        >>> make_teacher("success", discount=0.99).name
        'success(discount=0.99)'
    """
    if name not in TEACHERS:
        raise ValueError(f"unknown teacher {name!r}; choose one of {sorted(TEACHERS)}")
    return TEACHERS[name](**kwargs)


# --------------------------------------------------------------------------- label sets
def _num_pairs_total(n: int) -> int:
    return n * (n - 1) // 2


def _unrank_pairs(rank: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    # rank in [0, n(n-1)/2) -> (i, j), i < j, row-major over the upper triangle
    rows = torch.arange(n, dtype=torch.int64)
    row_start = rows * (2 * n - rows - 1) // 2
    i = torch.searchsorted(row_start, rank, right=True) - 1
    j = i + 1 + (rank - row_start[i])
    return i, j


def _segments(
    trajs: TensorDictBase, index: torch.Tensor, start: torch.Tensor, length: int
) -> TensorDict:
    """Rows ``index`` of ``trajs`` cut to ``[start, start + length)`` (``start + length <= H``)."""
    picked = trajs[index.to(trajs.device)]
    steps = (start[:, None] + torch.arange(length)[None, :]).to(trajs.device)  # [M, L]

    def cut(x: torch.Tensor) -> torch.Tensor:
        idx = steps.reshape(*steps.shape, *([1] * (x.ndim - 2))).expand(*steps.shape, *x.shape[2:])
        return x.gather(1, idx)

    return picked.apply(cut, batch_size=[index.shape[0], length])


def make_scripted_labels(
    trajs: TensorDictBase,
    *,
    num_pairs: int,
    teacher: ReturnTeacher,
    seed: int,
    segment_length: int | None = None,
) -> TensorDict:
    """Draw trajectory pairs and label them with a scripted teacher.

    Pairs are drawn **uniformly without replacement among the N(N-1)/2 unordered pairs of
    distinct trajectories** ``{i, j}, i != j``; which one becomes ``tau0`` is a fair coin.
    With ``segment_length=L`` each side is a segment of ``L`` steps starting uniformly in
    ``[0, max(n - L, 0)]`` of its valid steps (shorter trajectories give a segment whose mask
    ends early); otherwise sides are full trajectories ``[M, H]``. The paper uses full
    trajectories and :data:`METAWORLD_NUM_LABELS` (30) / :data:`LOCOMOTION_NUM_LABELS` (15) pairs.

    Args:
        trajs: ``[N, H]`` trajectory batch with the keys the teacher needs.
        num_pairs: number of labelled pairs ``M``.
        teacher: a scripted teacher (e.g. :class:`ReturnTeacher`); its ``name`` is stored.
        seed: seeds pair, orientation and segment draws (same seed, same labels).
        segment_length: optional segment length ``L <= H``.

    Returns:
        Label set ``[M]`` (module docstring) with ``index0/1``, ``start0/1`` and ``teacher``.

    Raises:
        ValueError: more pairs than exist, bad segment length, or a teacher ``horizon`` with
            segments.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=10, horizon=16, seed=0)
        >>> labels = make_scripted_labels(trajs, num_pairs=4, teacher=ReturnTeacher(), seed=1,
        ...                               segment_length=5)
        >>> labels["tau0"].batch_size
        torch.Size([4, 5])
    """
    validate_trajectories(trajs, name="make_scripted_labels trajectories")
    n, horizon = trajs.batch_size
    total = _num_pairs_total(n)
    if num_pairs < 1:
        raise ValueError(f"make_scripted_labels: num_pairs must be >= 1, got {num_pairs}")
    if num_pairs > total:
        raise ValueError(
            f"make_scripted_labels: asked for {num_pairs} pairs but {n} trajectories have only "
            f"{total} distinct pairs"
        )
    if segment_length is not None:
        if not 1 <= segment_length <= horizon:
            raise ValueError(
                f"make_scripted_labels: segment_length must be in [1, {horizon}], "
                f"got {segment_length}"
            )
        if getattr(teacher, "horizon", None) is not None:
            raise ValueError(
                "make_scripted_labels: a teacher with horizon= scores full trajectories, "
                "not segments"
            )
    i, j = draw_pairs(n, num_pairs, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    flip = torch.rand(num_pairs, generator=gen) < 0.5
    index0, index1 = torch.where(flip, j, i), torch.where(flip, i, j)
    if segment_length is None:
        return label_pairs(trajs, index0, index1, teacher=teacher)
    lengths = trajs.get("mask").sum(-1).cpu()

    def starts(index: torch.Tensor) -> torch.Tensor:
        high = (lengths[index] - segment_length).clamp(min=0)
        return (
            (torch.rand(index.shape[0], generator=gen, dtype=torch.float64) * (high + 1))
            .floor()
            .long()
        )

    start0, start1 = starts(index0), starts(index1)
    return label_pairs(trajs, index0, index1, teacher=teacher, start0=start0, start1=start1,
                       segment_length=segment_length)


def draw_pairs(n: int, num_pairs: int, *, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``num_pairs`` distinct unordered pairs ``(i, j), i < j`` of ``range(n)``, uniformly.

    Drawn without replacement among the ``n(n-1)/2`` pairs in ``O(num_pairs)`` memory (the
    pair draw of :func:`make_scripted_labels`; same seed, same pairs).

    Example:
        >>> i, j = draw_pairs(5, 3, seed=0)
        >>> bool((i < j).all()), i.shape
        (True, torch.Size([3]))
    """
    total = _num_pairs_total(n)
    if not 0 <= num_pairs <= total:
        raise ValueError(f"draw_pairs: asked for {num_pairs} pairs but {n} items have only {total} distinct pairs")
    rank = torch.tensor(random.Random(seed).sample(range(total), num_pairs), dtype=torch.int64)
    return _unrank_pairs(rank, n)


def label_pairs(
    trajs: TensorDictBase,
    index0: torch.Tensor,
    index1: torch.Tensor,
    *,
    teacher: ReturnTeacher,
    start0: torch.Tensor | None = None,
    start1: torch.Tensor | None = None,
    segment_length: int | None = None,
) -> TensorDict:
    """Label given pairs of dataset trajectories (or segments) with a scripted teacher.

    The one place a label set is assembled from indices: :func:`make_scripted_labels` (uniform
    pairs) and :func:`torchrl_ftb.preference.make_query_labels` (actively chosen pairs) both
    call it.

    Args:
        trajs: ``[N, H]`` trajectory batch with the keys the teacher needs.
        index0, index1: ``[M]`` int64 trajectory indices of ``tau0`` / ``tau1``.
        teacher: a scripted teacher; its ``name`` is stored.
        start0, start1: ``[M]`` first steps of the segments (with ``segment_length``;
            default: full trajectories, start 0).
        segment_length: segment length ``L`` (``start + L <= H``); ``None``: full trajectories.

    Returns:
        Label set ``[M]`` (module docstring) with ``index0/1``, ``start0/1`` and ``teacher``.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=6, horizon=8, seed=0)
        >>> labels = label_pairs(trajs, torch.tensor([0, 2]), torch.tensor([1, 5]), teacher=ReturnTeacher())
        >>> labels["tau1"].batch_size, labels["index1"].tolist()
        (torch.Size([2, 8]), [1, 5])
    """
    index0, index1 = torch.as_tensor(index0, dtype=torch.int64).cpu(), torch.as_tensor(index1, dtype=torch.int64).cpu()
    n, horizon = trajs.batch_size
    if index0.shape != index1.shape or index0.ndim != 1:
        raise ValueError(f"label_pairs: index0 and index1 must be [M] of one shape, got {list(index0.shape)} "
                         f"and {list(index1.shape)}")
    if index0.numel() and (min(index0.min(), index1.min()) < 0 or max(index0.max(), index1.max()) >= n):
        raise ValueError(f"label_pairs: trajectory indices must be in [0, {n})")
    length = horizon if segment_length is None else int(segment_length)
    start0 = torch.zeros_like(index0) if start0 is None else torch.as_tensor(start0, dtype=torch.int64).cpu()
    start1 = torch.zeros_like(index1) if start1 is None else torch.as_tensor(start1, dtype=torch.int64).cpu()
    tau0 = _segments(trajs, index0, start0, length)
    tau1 = _segments(trajs, index1, start1, length)
    labels = TensorDict(
        {
            "tau0": tau0,
            "tau1": tau1,
            "label": teacher(tau0, tau1).to(torch.float32),
            "index0": index0,
            "index1": index1,
            "start0": start0,
            "start1": start1,
        },
        batch_size=[index0.shape[0]],
        device=trajs.device,
    )
    labels.set_non_tensor("teacher", teacher.name)
    return labels


def validate_labels(
    labels: TensorDictBase,
    *,
    name: str = "labels",
    obs_dim: int | None = None,
    action_dim: int | None = None,
) -> TensorDictBase:
    """Check a label set (module docstring); raise a ValueError naming ``name`` and the field.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> labels = make_scripted_labels(make_toy_dataset(num_trajectories=4, horizon=4),
        ...                               num_pairs=2, teacher=ReturnTeacher(), seed=0)
        >>> validate_labels(labels, obs_dim=3) is labels
        True
    """
    if labels.batch_dims != 1:
        raise ValueError(f"{name}: a label set has batch_size [M], got {list(labels.batch_size)}")
    for key in ("tau0", "tau1", "label"):
        if key not in labels.keys():
            raise ValueError(f"{name}: missing {key!r}")
    m = labels.batch_size[0]
    for side in ("tau0", "tau1"):
        validate_trajectories(
            labels.get(side), name=f"{name}[{side!r}]", obs_dim=obs_dim, action_dim=action_dim
        )
    for key in ("observation", "action"):
        d0, d1 = labels.get(("tau0", key)).shape[-1], labels.get(("tau1", key)).shape[-1]
        if d0 != d1:
            raise ValueError(f"{name}: {key!r} has dimension {d0} in tau0 but {d1} in tau1")
    label = labels.get("label")
    if label.shape != (m,) or not label.is_floating_point():
        raise ValueError(
            f"{name}: 'label' must be float [{m}], got {label.dtype} {list(label.shape)}"
        )
    bad = ~torch.isin(label, torch.tensor(_LABEL_VALUES, dtype=label.dtype, device=label.device))
    if bool(bad.any()):
        raise ValueError(
            f"{name}: 'label' values must be in {{0, 0.5, 1}}, "
            f"found {label[bad].unique().tolist()[:5]}"
        )
    for key in ("index0", "index1", "start0", "start1"):
        if key in labels.keys():
            value = labels.get(key)
            if value.shape != (m,) or value.dtype != torch.int64:
                raise ValueError(
                    f"{name}: {key!r} must be int64 [{m}], got {value.dtype} {list(value.shape)}"
                )
    return labels


def check_labels_match(
    labels: TensorDictBase, trajs: TensorDictBase, *, name: str = "labels"
) -> None:
    """Raise a clear ValueError if a label set does not belong to the dataset ``trajs``.

    Checks observation/action sizes, that ``index0``/``index1`` are valid trajectory indices,
    and that each labelled side equals the dataset trajectory (segment at ``start0``/``start1``,
    0 if absent) on its valid steps. Label sets without indices (e.g. PT files) are checked
    on sizes only.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=6, horizon=8, seed=0)
        >>> labels = make_scripted_labels(trajs, num_pairs=3, teacher=ReturnTeacher(), seed=0)
        >>> check_labels_match(labels, trajs)  # no error
    """
    validate_trajectories(trajs, name=f"{name}: dataset")
    validate_labels(
        labels,
        name=name,
        obs_dim=trajs.get("observation").shape[-1],
        action_dim=trajs.get("action").shape[-1],
    )
    n, horizon = trajs.batch_size
    for side, idx_key, start_key in (("tau0", "index0", "start0"), ("tau1", "index1", "start1")):
        if idx_key not in labels.keys():
            continue
        index = labels.get(idx_key).cpu()
        if bool(((index < 0) | (index >= n)).any()):
            raise ValueError(
                f"{name}: {idx_key!r} has indices outside [0, {n}) (max {int(index.max())}): "
                "the labels were made for another dataset"
            )
        seg = labels.get(side)
        length = seg.batch_size[1]
        start = (
            labels.get(start_key).cpu() if start_key in labels.keys() else torch.zeros_like(index)
        )
        if bool(((start < 0) | (start + length > horizon)).any()):
            raise ValueError(
                f"{name}: {side!r} segments of length {length} from {start_key!r} do not fit the "
                f"dataset horizon {horizon}"
            )
        ref = _segments(trajs, index, start, length)
        seg_mask = seg.get("mask").to(ref.device)
        for key in ("observation", "action"):
            a, b = seg.get(key).to(ref.device), ref.get(key)
            close = torch.isclose(a, b, atol=1e-5, rtol=1e-5).all(-1) | ~seg_mask
            if not bool(close.all()):
                pair = int((~close).any(-1).nonzero()[0])
                raise ValueError(
                    f"{name}: pair {pair} {side!r} {key!r} differs from dataset trajectory "
                    f"{int(index[pair])} "
                    f"(start {int(start[pair])}): the labels were made for another dataset"
                )
        if bool((seg_mask & ~ref.get("mask")).any()):
            raise ValueError(
                f"{name}: {side!r} has valid steps where the dataset trajectory has none"
            )


# --------------------------------------------------------------------------- PT / IPL files
_PT_KEYS = ("obs_1", "obs_2", "action_1", "action_2", "label")


def load_pt_labels(
    path: str | os.PathLike,
    *,
    obs_dim: int | None = None,
    action_dim: int | None = None,
    teacher: str | None = None,
) -> TensorDict:
    """Load a Preference-Transformer / IPL label file (``npz``) as a label set.

    The file holds ``obs_1``, ``obs_2`` ``[M, L, obs]``, ``action_1``, ``action_2``
    ``[M, L, act]`` and ``label`` ``[M]`` in {0, 0.5, 1}, label 1 meaning the *second*
    segment is preferred — the same orientation as ours, so ``tau0 = (obs_1, action_1)``,
    ``tau1 = (obs_2, action_2)`` and ``label`` is copied. Segments are full (mask all True);
    the files carry no reward and no dataset indices.

    Args:
        path: the ``.npz`` file.
        obs_dim: expected observation size, checked if given.
        action_dim: expected action size, checked if given.
        teacher: name stored as ``"teacher"`` (default ``"pt-file:<file stem>"``).

    Raises:
        FileNotFoundError: no file.
        ValueError: missing keys, shape mismatches, labels outside {0, 0.5, 1}, NaNs, or
            dimensions different from ``obs_dim``/``action_dim``.

    Example:
        >>> labels = load_pt_labels("num100_human_train.npz", obs_dim=11)  # doctest: +SKIP
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such label file")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in _PT_KEYS if k not in data.files]
            if missing:
                raise ValueError(f"{path}: missing key(s) {missing} (has {sorted(data.files)})")
            arrays = {k: np.asarray(data[k]) for k in _PT_KEYS}
    except NPZ_READ_ERRORS as err:
        raise ValueError(f"{path}: not a readable npz file ({type(err).__name__}: {err})") from err
    for a, b in (("obs_1", "obs_2"), ("action_1", "action_2")):
        if arrays[a].shape != arrays[b].shape:
            raise ValueError(
                f"{path}: {a!r} has shape {list(arrays[a].shape)} but {b!r} has "
                f"{list(arrays[b].shape)}"
            )
        if arrays[a].ndim != 3:
            raise ValueError(
                f"{path}: {a!r} must have shape [M, L, D], got {list(arrays[a].shape)}"
            )
    m, seg_len = arrays["obs_1"].shape[:2]
    if arrays["action_1"].shape[:2] != (m, seg_len):
        raise ValueError(
            f"{path}: 'action_1' has shape {list(arrays['action_1'].shape)} but 'obs_1' has "
            f"{list(arrays['obs_1'].shape)} (first two dimensions must match)"
        )
    label = (
        arrays["label"].reshape(-1)
        if arrays["label"].ndim == 2 and arrays["label"].shape[1] == 1
        else arrays["label"]
    )
    if label.shape != (m,):
        raise ValueError(
            f"{path}: 'label' must have shape [{m}], got {list(arrays['label'].shape)}"
        )
    if not np.isin(label, _LABEL_VALUES).all():
        bad = np.unique(label[~np.isin(label, _LABEL_VALUES)])[:5]
        raise ValueError(f"{path}: 'label' values must be in {{0, 0.5, 1}}, found {bad.tolist()}")
    for key in _PT_KEYS[:4]:
        if not np.isfinite(arrays[key]).all():
            raise ValueError(f"{path}: {key!r} has NaN or inf values")
    if obs_dim is not None and arrays["obs_1"].shape[-1] != obs_dim:
        raise ValueError(
            f"{path}: 'obs_1' has dimension {arrays['obs_1'].shape[-1]} but obs_dim={obs_dim} "
            "was expected (labels for another environment?)"
        )
    if action_dim is not None and arrays["action_1"].shape[-1] != action_dim:
        raise ValueError(
            f"{path}: 'action_1' has dimension {arrays['action_1'].shape[-1]} but "
            f"action_dim={action_dim} was expected"
        )

    def side(obs: np.ndarray, act: np.ndarray) -> TensorDict:
        return TensorDict(
            {
                "observation": torch.as_tensor(obs, dtype=torch.float32),
                "action": torch.as_tensor(act, dtype=torch.float32),
                "mask": torch.ones(m, seg_len, dtype=torch.bool),
            },
            batch_size=[m, seg_len],
        )

    labels = TensorDict(
        {
            "tau0": side(arrays["obs_1"], arrays["action_1"]),
            "tau1": side(arrays["obs_2"], arrays["action_2"]),
            "label": torch.as_tensor(label, dtype=torch.float32),
        },
        batch_size=[m],
    )
    labels.set_non_tensor("teacher", teacher if teacher is not None else f"pt-file:{path.stem}")
    return validate_labels(labels, name=str(path))


# --------------------------------------------------------------------------- persistence
def _teacher_names(labels: TensorDictBase) -> list:
    if "teacher" not in labels.keys():
        return []
    value = labels["teacher"]  # a str, or a list of str after concatenating label sets
    return sorted({value} if isinstance(value, str) else {str(v) for v in value})


def save_labels(
    labels: TensorDictBase, path: str | os.PathLike, *, meta: dict | None = None
) -> Path:
    """Persist a label set as a memmap folder plus ``meta.json``, atomically.

    The folder is written under a temporary name and swapped in at the end; ``meta.json``
    records the format version, number of pairs, segment length and teacher name(s).

    Example:
        >>> import tempfile, os
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> labels = make_scripted_labels(make_toy_dataset(num_trajectories=4, horizon=4),
        ...                               num_pairs=2, teacher=ReturnTeacher(), seed=0)
        >>> path = save_labels(labels, os.path.join(tempfile.mkdtemp(), "labels"))
        >>> load_labels(path)[1]["teacher"]
        ['return']
    """
    path = Path(path)
    validate_labels(labels, name=str(path))
    with atomic_directory(path) as tmp:
        labels.memmap(tmp / "data")
        full_meta = {
            "format_version": LABELS_FORMAT_VERSION,
            "num_pairs": int(labels.batch_size[0]),
            "segment_length": int(labels.get("tau0").batch_size[1]),
            "teacher": _teacher_names(labels),
            **(meta or {}),
        }
        # written last: its presence marks a complete label set
        atomic_write_text(tmp / "meta.json", json.dumps(full_meta, indent=2, default=str))
    return path


def load_labels(path: str | os.PathLike) -> tuple[TensorDict, dict]:
    """Load a label set written by :func:`save_labels` (into memory) and validate it.

    Returns:
        ``(labels, meta)``.

    Raises:
        FileNotFoundError: no complete label set at ``path``.
        ValueError: unknown format version or malformed content.
    """
    path = Path(path)
    labels, meta = read_memmap_folder(path, what="label set", format_version=LABELS_FORMAT_VERSION)
    return validate_labels(labels, name=str(path)), meta
