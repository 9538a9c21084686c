"""Padded trajectory batches: the data structure every FTB stage exchanges.

A set of ``N`` trajectories padded to a horizon ``H`` is a :class:`~tensordict.TensorDict`
with ``batch_size=[N, H]``, torchrl key names and a boolean ``"mask"`` that is ``True`` on
valid steps (always a prefix). See ``docs/conventions.md`` for the full key table.

Example:
    >>> import torch
    >>> from torchrl_ftb.data import flat_to_trajectories, trajectories_to_flat
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=4, horizon=8, seed=0)
    >>> trajs.batch_size
    torch.Size([4, 8])
    >>> flat = trajectories_to_flat(trajs)
    >>> bool((flat.batch_size[0] == trajectory_lengths(trajs).sum()))
    True
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Any, Iterator, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors.utils import split_trajectories

__all__ = [
    "FORMAT_VERSION",
    "NPZ_READ_ERRORS",
    "REQUIRED_KEYS",
    "REWARD_KEY",
    "TERMINATED_KEY",
    "trajectory_lengths",
    "stop_rule_fill",
    "success_streak_length",
    "validate_trajectories",
    "flat_to_trajectories",
    "trajectories_to_flat",
    "pad_trajectories",
    "coarsen_trajectories",
    "refine_trajectories",
    "read_memmap_folder",
    "save_trajectories",
    "load_trajectories",
    "atomic_directory",
    "atomic_file",
    "atomic_torch_save",
    "read_checkpoint",
    "atomic_write_text",
    "sampler_rng_state",
    "restore_sampler_rng",
]

FORMAT_VERSION = 1
REQUIRED_KEYS: tuple = ("observation", "action", "mask")
REWARD_KEY = ("next", "reward")
TERMINATED_KEY = ("next", "terminated")
_BOOL_NEXT_KEYS = ("done", "terminated", "truncated", "success")


def trajectory_lengths(td: TensorDictBase) -> torch.Tensor:
    """Number of valid steps of each trajectory of an ``[N, H]`` batch (``int64 [N]``)."""
    return td.get("mask").sum(-1)


def stop_rule_fill(
    mask: torch.Tensor,
    *,
    horizon: int,
    discount: float = 1.0,
    terminated: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where and how much a trajectory cut short by a stop rule keeps earning up to ``horizon`` steps.

    The one definition of the stop-rule fill shared by the teachers' true return and the score
    model: a trajectory whose last valid step ``n - 1`` is not terminated keeps earning that step's
    reward until step ``horizon - 1``, i.e. that reward times ``sum_{h=n}^{horizon-1} gamma^h``.

    Args:
        mask: ``bool [*B, H]`` valid steps.
        horizon: the fill's horizon (>= 1).
        discount: ``gamma`` in (0, 1].
        terminated: optional ``bool [*B, H]`` per-step termination flags; a trajectory terminated
            at its last valid step gets no fill (absent: none is).

    Returns:
        ``(last, weight)``: the index of each trajectory's last valid step (``int64 [*B]``, 0 where
        there is none) and the weight of its reward (``float64 [*B]``; 0 for empty, terminated or
        already ``>= horizon`` trajectories).

    Example:
        >>> mask = torch.tensor([[True, True, False, False], [True, True, True, True]])
        >>> stop_rule_fill(mask, horizon=6)
        (tensor([1, 3]), tensor([4., 2.], dtype=torch.float64))
    """
    if horizon < 1:
        raise ValueError(f"stop_rule_fill: horizon must be >= 1, got {horizon}")
    steps = mask.shape[-1]
    position = torch.arange(steps, device=mask.device).expand_as(mask)
    last = torch.where(mask, position, torch.full_like(position, -1)).amax(-1)  # -1: no valid step
    span = max(horizon, steps)
    weights = float(discount) ** torch.arange(span, dtype=torch.float64, device=mask.device)
    cum = torch.cat([weights.new_zeros(1), torch.cumsum(weights, 0)])  # cum[k] = sum_{h<k} gamma^h
    weight = cum[horizon] - cum[(last + 1).clamp(max=horizon)]
    keep = last >= 0
    last = last.clamp(min=0)
    if terminated is not None:
        keep = keep & ~terminated.reshape(mask.shape).bool().gather(-1, last[..., None]).squeeze(-1)
    return last, weight * keep


def success_streak_length(success: torch.Tensor, mask: torch.Tensor, *, streak: int) -> torch.Tensor:
    """Where a success-streak stop rule would have ended each trajectory: its length in steps.

    Our Meta-World episodes stop once ``streak`` consecutive steps succeed (the step that completes
    the streak is the last one kept). A generated trajectory is not cut by that rule, so scoring it
    with the stop-rule fill (:func:`stop_rule_fill`) without cutting it first measures it under
    another protocol than the data: this gives the cut.

    Args:
        success: ``bool [*B, H]`` per-step success flags.
        mask: ``bool [*B, H]`` valid steps (a prefix).
        streak: consecutive successes that end an episode (>= 1).

    Returns:
        ``int64 [*B]``: the step count up to and including the step that completes the first streak,
        or the trajectory's own length where no streak completes.

    Example:
        >>> success = torch.tensor([[False, True, True, True, False], [True, False, True, False, True]])
        >>> success_streak_length(success, torch.ones(2, 5, dtype=torch.bool), streak=2)
        tensor([3, 5])
    """
    first = _first_streak_end(success, mask, streak=streak)
    return torch.where(first < mask.shape[-1], first + 1, mask.long().sum(-1))


def success_streak_fired(success: torch.Tensor, mask: torch.Tensor, *, streak: int) -> torch.Tensor:
    """Whether the success-streak stop rule ends each trajectory (``bool [*B]``).

    A recorded episode shorter than its time limit always ended this way; a generated trajectory
    may end early without it (its length is where the diffuser's padding starts), and then no
    stop rule ended it: the stop-rule fill (:func:`stop_rule_fill`) does not apply to it.

    Example:
        >>> success = torch.tensor([[False, True, True, False], [True, False, True, False]])
        >>> success_streak_fired(success, torch.ones(2, 4, dtype=torch.bool), streak=2)
        tensor([ True, False])
    """
    return _first_streak_end(success, mask, streak=streak) < mask.shape[-1]


def _first_streak_end(success: torch.Tensor, mask: torch.Tensor, *, streak: int) -> torch.Tensor:
    """Index of the step completing the first ``streak`` consecutive valid successes (``H``: none)."""
    if streak < 1:
        raise ValueError(f"success streak: streak must be >= 1, got {streak}")
    if success.shape != mask.shape:
        raise ValueError(f"success streak: success {tuple(success.shape)} and mask {tuple(mask.shape)} "
                         "differ in shape")
    ok = (success.bool() & mask.bool()).long()
    # run[h] = consecutive successes ending at h: cumulative count minus the count at the last failure
    count = ok.cumsum(-1)
    at_failure = torch.where(ok.bool(), torch.zeros_like(count), count)
    run = count - at_failure.cummax(-1).values
    steps = mask.shape[-1]
    return torch.where(run >= streak, torch.arange(steps, device=mask.device).expand_as(run),
                       torch.full_like(count, steps)).amin(-1)


def validate_trajectories(
    td: TensorDictBase,
    *,
    name: str = "trajectories",
    obs_dim: int | None = None,
    action_dim: int | None = None,
    require: Sequence = (),
) -> TensorDictBase:
    """Check that ``td`` is a well-formed padded trajectory batch; raise a clear error if not.

    Args:
        td: the ``[N, H]`` batch.
        name: how to call the data in error messages (e.g. the file it came from).
        obs_dim: expected observation size (e.g. the env's), checked if given.
        action_dim: expected action size, checked if given.
        require: extra keys that must be present (e.g. ``[("next", "reward")]``).

    Returns:
        ``td`` itself, for chaining.

    Raises:
        ValueError: missing key, wrong rank/shape, non-finite values on valid steps, or a
            mask that is not a prefix.
    """
    if td.batch_dims != 2:
        raise ValueError(
            f"{name}: expected a padded trajectory batch with batch_size [N, H], "
            f"got batch_size {list(td.batch_size)}"
        )
    keys = set(td.keys(include_nested=True, leaves_only=True))
    for key in (*REQUIRED_KEYS, *require):
        if key not in keys:
            raise ValueError(f"{name}: missing required key {key!r} (has {sorted(map(str, keys))})")
    mask = td.get("mask")
    if mask.dtype != torch.bool:
        raise ValueError(f"{name}: 'mask' must be bool, got {mask.dtype}")
    if mask.shape != td.batch_size:
        raise ValueError(f"{name}: 'mask' must have shape {list(td.batch_size)}, got {list(mask.shape)}")
    # valid steps must be a prefix: once False, never True again
    if mask.shape[-1] > 1 and bool((mask[..., 1:] & ~mask[..., :-1]).any()):
        raise ValueError(f"{name}: 'mask' is not a prefix of valid steps for some trajectory")
    if bool((mask.sum(-1) == 0).any()):
        raise ValueError(f"{name}: some trajectories have zero valid steps")
    for key, dim, what in (("observation", obs_dim, "obs_dim"), ("action", action_dim, "action_dim")):
        value = td.get(key)
        if value.ndim != 3:
            raise ValueError(f"{name}: {key!r} must have shape [N, H, D], got {list(value.shape)}")
        if dim is not None and value.shape[-1] != dim:
            raise ValueError(
                f"{name}: {key!r} has last dimension {value.shape[-1]} but {what}={dim} was expected "
                "(does the dataset match the environment?)"
            )
    for key in keys:
        value = td.get(key)
        if value.is_floating_point() and not bool(torch.isfinite(value[mask]).all()):
            raise ValueError(f"{name}: field {key!r} has NaN or inf values on valid steps")
    return td


def flat_to_trajectories(
    flat: TensorDictBase,
    *,
    done_key: Any = "done",
    trajectory_key: Any = None,
) -> TensorDict:
    """Split flat transitions ``[T]`` (torchrl layout) into a padded ``[N, H]`` batch.

    Uses :func:`torchrl.collectors.utils.split_trajectories`; episodes end where
    ``("next", done_key)`` is True (or where ``trajectory_key`` changes if given).

    Args:
        flat: a ``[T]`` TensorDict with ``observation``, ``action`` and ``("next", ...)`` entries.
        done_key: key under ``"next"`` that ends an episode.
        trajectory_key: optional per-step episode id key (takes precedence over ``done_key``).

    Returns:
        An ``[N, H]`` TensorDict with a bool ``"mask"``; helper keys torchrl adds are removed.
    """
    if flat.batch_dims != 1:
        raise ValueError(f"flat transitions must have batch_size [T], got {list(flat.batch_size)}")
    if trajectory_key is None and ("next", done_key) not in flat.keys(True):
        raise ValueError(f"flat transitions: missing key ('next', {done_key!r}) to split episodes")
    flat = flat.clone(False)
    if trajectory_key is None:
        # make sure the last step closes an episode so the tail is not dropped or merged
        done = flat.get(("next", done_key)).clone()
        done[-1] = True
        flat.set(("next", done_key), done)
    out = split_trajectories(flat, done_key=done_key if trajectory_key is None else None,
                             trajectory_key=trajectory_key)
    for extra in ("traj_ids", ("collector", "mask"), ("collector", "traj_ids")):
        if extra in out.keys(True):
            out = out.exclude(extra)
    mask = out.get("mask")
    if mask.dtype != torch.bool:
        out.set("mask", mask.bool())
    return out


def trajectories_to_flat(td: TensorDictBase) -> TensorDict:
    """Valid steps of an ``[N, H]`` batch as flat transitions ``[sum(lengths)]`` (mask removed).

    Order is trajectory-major, so ``("next", "done")`` (if present) still ends each episode.
    """
    mask = td.get("mask")
    return td[mask].exclude("mask")


def pad_trajectories(trajs: Sequence[TensorDictBase], *, horizon: int | None = None) -> TensorDict:
    """Stack variable-length ``[T_i]`` trajectories into one ``[N, H]`` batch with a mask.

    Args:
        trajs: flat per-episode TensorDicts (same keys).
        horizon: pad length; defaults to the longest episode. Longer episodes raise.
    """
    if not len(trajs):
        raise ValueError("pad_trajectories: no trajectories given")
    lengths = [int(t.batch_size[0]) for t in trajs]
    horizon = max(lengths) if horizon is None else horizon
    if max(lengths) > horizon:
        raise ValueError(f"pad_trajectories: episode of length {max(lengths)} exceeds horizon {horizon}")
    padded = []
    for t, n in zip(trajs, lengths):
        t = t.exclude("mask") if "mask" in t.keys() else t
        p = t[:1].expand(horizon).clone().zero_()
        p[:n] = t
        p.set("mask", torch.arange(horizon) < n)
        padded.append(p)
    return torch.stack(padded, 0).contiguous()


def _at_steps(value: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """``value [N, H, ...]`` at per-trajectory step indices ``steps [N, L]``: ``[N, L, ...]``."""
    shape = (*steps.shape, *([1] * (value.dim() - 2)))
    return value.gather(1, steps.reshape(shape).expand(*steps.shape, *value.shape[2:]))


def coarsen_trajectories(td: TensorDictBase, stride: int, *, average: Sequence[str] = ("action",)) -> TensorDict:
    """Every ``stride``-th step of an ``[N, H]`` batch, and each trajectory's last step: ``[N, ceil(H / stride)]``.

    A trajectory of length ``n`` keeps ``m = ceil(n / stride)`` valid steps (its mask stays a prefix): steps
    ``0, stride, ..., (m - 2) * stride`` and its last step ``n - 1`` in place of ``(m - 1) * stride``. The last
    step is kept because an episode's end is what it earned: a Meta-World episode ends at its success, and a round
    trip that dropped it would drop the success. The keys in ``average`` (default: the action) are the mean over
    the steps from one kept step to the next (the last kept step: its own value): the net push that moves the
    state from one kept step to the next, which is what a held action of :func:`refine_trajectories` has to
    reproduce along the interpolated path (a single noisy action picked from the window would not).

    Temporal coarsening shortens what a diffuser has to model by ``stride`` (FTB's authors name compression as
    the way to long horizons, §6); :func:`refine_trajectories` maps back.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.arange(8.0).reshape(1, 8, 1), "action": torch.ones(1, 8, 1),
        ...                  "mask": torch.arange(8).reshape(1, 8) < 6}, batch_size=[1, 8])
        >>> coarse = coarsen_trajectories(td, 3)
        >>> coarse["observation"][0, :, 0].tolist(), coarse["mask"][0].tolist()
        ([0.0, 5.0, 6.0], [True, True, False])
        >>> refine_trajectories(coarse, 3, horizon=8)["mask"].sum().item()  # never shorter than the original 6
        6
    """
    stride = int(stride)
    if stride < 1:
        raise ValueError(f"coarsen_trajectories: stride must be >= 1, got {stride}")
    if stride == 1:  # the identity (the window means below are exact only up to float rounding)
        return td.clone()
    mask = td.get("mask").bool()
    n, horizon = mask.shape
    lengths = mask.sum(-1, keepdim=True)  # [N, 1]
    times = torch.arange(0, horizon, stride, device=mask.device).unsqueeze(0).expand(n, -1)  # [N, L]
    valid = times < lengths
    is_last = valid & (times + stride >= lengths)
    times = torch.where(is_last, lengths - 1, times)

    ends = torch.where(valid & ~is_last, torch.cat([times[:, 1:], times[:, -1:]], 1), times + 1)  # window ends
    out = td.exclude("mask").apply(lambda value: _at_steps(value, times), batch_size=[n, times.shape[1]])
    for key in average:
        value = td.get(key)
        cum = torch.cat([torch.zeros_like(value[:, :1]), value.cumsum(1)], 1)  # cum[:, t] = sum of steps < t
        width = (ends - times).clamp(min=1).reshape(*times.shape, *([1] * (value.dim() - 2)))
        out.set(key, (_at_steps(cum, ends.clamp(max=horizon)) - _at_steps(cum, times)) / width)
    out.set("mask", valid)
    return out


def refine_trajectories(td: TensorDictBase, stride: int, *, horizon: int,
                        interpolate: Sequence[str] = ("observation",)) -> TensorDict:
    """Back from a coarsened ``[N, L]`` batch to ``[N, horizon]``: the inverse of :func:`coarsen_trajectories`
    up to what the dropped steps held.

    Coarse step ``j`` sits at time ``j * stride``. The keys in ``interpolate`` are interpolated linearly between
    consecutive valid coarse steps; every other key of ``td`` (actions, flags) is held from the coarse step at or
    before each time. A trajectory with ``m`` valid coarse steps reaches its last state at ``(m - 1) * stride`` and
    holds it to length ``m * stride`` (capped at ``horizon``). A round trip of a length-``n`` trajectory keeps its
    first and last states; its last segment runs up to ``stride - 1`` steps faster and its end state is held up to
    ``stride - 1`` steps longer, so it is never shorter than ``n`` (a shorter one would cut a success streak that
    ended the episode: :func:`torchrl_ftb.data.success_streak_fired`).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> coarse = TensorDict({"observation": torch.tensor([[[0.0], [3.0], [9.0]]]),
        ...                      "mask": torch.tensor([[True, True, False]])}, batch_size=[1, 3])
        >>> fine = refine_trajectories(coarse, 3, horizon=6)
        >>> fine["observation"][0, :, 0].tolist(), fine["mask"][0].tolist()
        ([0.0, 1.0, 2.0, 3.0, 3.0, 3.0], [True, True, True, True, True, True])
    """
    stride = int(stride)
    if stride < 1:
        raise ValueError(f"refine_trajectories: stride must be >= 1, got {stride}")
    mask = td.get("mask").bool()
    n, coarse_len = mask.shape
    valid = mask.sum(-1)  # [N] valid coarse steps (a prefix)
    t = torch.arange(horizon, device=mask.device)
    last = (valid - 1).clamp(min=0).unsqueeze(-1)  # [N, 1] index of the last valid coarse step
    j = (t // stride).unsqueeze(0).expand(n, horizon).clamp(max=coarse_len - 1)
    j = torch.minimum(j, last)  # past the end: hold the last valid step
    j_next = torch.minimum(j + 1, last)
    frac = ((t % stride).float() / stride).unsqueeze(0).expand(n, horizon)
    frac = torch.where(j_next > j, frac, torch.zeros_like(frac))
    lengths = (valid * stride).clamp(max=horizon)
    out = {}
    for key in td.keys():
        if key == "mask":
            continue
        value = td.get(key)
        if not isinstance(value, torch.Tensor):
            raise ValueError(f"refine_trajectories: key {key!r} is nested; refine leaf tensors only")
        held = _at_steps(value, j)
        if key in interpolate:
            w = frac.reshape(n, horizon, *([1] * (value.dim() - 2))).to(value.dtype)
            held = held + w * (_at_steps(value, j_next) - held)
        out[key] = held
    out["mask"] = t.unsqueeze(0) < lengths.unsqueeze(-1)
    return TensorDict(out, batch_size=[n, horizon], device=td.device)


def hold_last_step(td: TensorDictBase, *, zero: Sequence[str] = ("action",)) -> TensorDict:
    """Each trajectory of a padded ``[N, H]`` batch continued to the full horizon by holding its last step.

    The padded steps ``t >= n`` of a length-``n`` trajectory become valid steps (the mask is all True) that repeat
    step ``n - 1``, except the keys in ``zero`` (default: the action), which are 0 there. On Meta-World (actions
    move the hand by a position delta) a zero action holds the hand where it is, so the continuation is the state
    the episode ended in, held: what the stop-rule fill (:func:`stop_rule_fill`) already assumes of the return.
    A model of held batches has no length to generate: the end of a trajectory is a stationary state instead of a
    jump to padding, and the success-streak stop rule cuts a generated one again
    (:func:`torchrl_ftb.flow.masked_true_returns` with ``streaks``).

    Args:
        td: ``[N, H]`` batch with a prefix ``mask``; every trajectory has at least one valid step. Nested keys
            (e.g. ``("next", "reward")``) are held too.

    Keyword Args:
        zero: keys set to 0 on the held steps.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.arange(4.0).reshape(1, 4, 1), "action": torch.ones(1, 4, 1),
        ...                  "mask": torch.tensor([[True, True, False, False]])}, batch_size=[1, 4])
        >>> held = hold_last_step(td)
        >>> held["observation"][0, :, 0].tolist(), held["action"][0, :, 0].tolist(), held["mask"].all().item()
        ([0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 0.0, 0.0], True)
    """
    mask = td.get("mask").bool()
    kept = td.exclude("mask")
    missing = [key for key in zero if key not in kept.keys(True)]
    if missing:
        raise ValueError(f"hold_last_step: zero={list(zero)} names keys the batch does not have: {missing}")
    lengths = mask.sum(-1, keepdim=True)  # [N, 1]
    if bool((lengths == 0).any()):
        raise ValueError(f"hold_last_step: trajectories {torch.nonzero(lengths[:, 0] == 0).flatten().tolist()[:10]} "
                         "have no valid step to hold")
    n, horizon = mask.shape
    t = torch.arange(horizon, device=mask.device).unsqueeze(0).expand(n, -1)
    steps = torch.minimum(t, lengths - 1)  # [N, H]: the step each time repeats
    out = kept.apply(lambda value: _at_steps(value, steps), batch_size=[n, horizon])
    held = t >= lengths
    for key in zero:
        value = out.get(key)
        out.set(key, value * ~held.reshape(*held.shape, *([1] * (value.dim() - 2))))
    out.set("mask", torch.ones_like(mask))
    return out


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temp file beside ``path`` (same suffix) that replaces ``path`` only on success.

    Example:
        >>> import tempfile, os
        >>> target = os.path.join(tempfile.mkdtemp(), "x.txt")
        >>> with atomic_file(target) as tmp:
        ...     _ = tmp.write_text("hello")
        >>> open(target).read()
        'hello'
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix or ".tmp")
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


_SWAP_ATTEMPTS = 5  # atomic_directory: tries of the final swap when concurrent writers interleave

# what numpy raises on a damaged .npz (a truncated zip, a bad member, a non-zip file), for loaders that name the file
NPZ_READ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temp directory beside ``path`` that is swapped in for ``path`` only on success.

    An interrupted write leaves ``path`` as it was (absent or the previous version) and
    removes the temp directory; an existing ``path`` is replaced (moved to a uniquely named
    backup beside it, then removed). Two processes writing the same ``path`` at once (e.g. two
    runs building one dataset cache entry) both succeed, the last one's version kept: a
    version that appears between the move and the swap is moved aside in turn.

    Example:
        >>> import tempfile
        >>> target = Path(tempfile.mkdtemp()) / "entry"
        >>> for text in ("first", "second"):
        ...     with atomic_directory(target) as tmp:
        ...         _ = (tmp / "x.txt").write_text(text)
        >>> (target / "x.txt").read_text(), sorted(p.name for p in target.parent.iterdir())
        ('second', ['entry'])
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        yield tmp
        for attempt in range(_SWAP_ATTEMPTS):
            old = None
            if path.exists():
                old = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old"))
                with contextlib.suppress(FileNotFoundError):  # another writer moved it away first
                    os.replace(path, old)
            try:
                os.replace(tmp, path)
                break
            except OSError:  # another writer's version landed in between: move that one aside too
                if attempt == _SWAP_ATTEMPTS - 1:
                    raise
            finally:
                if old is not None:
                    shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temp file in the same folder + ``os.replace``)."""
    with atomic_file(path) as tmp:
        tmp.write_text(text)


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> None:
    """``torch.save`` to a temp file then ``os.replace``: a crash never leaves a half file."""
    with atomic_file(path) as tmp:
        torch.save(obj, tmp)


def sampler_rng_state(buffer: Any) -> torch.Tensor | None:
    """The state of a replay buffer's own sampling generator (torchrl's ``ReplayBuffer(generator=)``), for a
    checkpoint, so a resumed run draws the batches an uninterrupted one would; ``None`` for a buffer without one
    (a plain callable, or a buffer that samples from torch's global RNG)."""
    rng = getattr(buffer, "_rng", None)  # torchrl keeps the generator here; it offers set_rng, no getter
    return rng.get_state() if isinstance(rng, torch.Generator) else None


def restore_sampler_rng(buffer: Any, state: torch.Tensor | None) -> None:
    """Put back a state from :func:`sampler_rng_state` (no-op for ``None`` or a buffer without a generator)."""
    rng = getattr(buffer, "_rng", None)
    if state is not None and isinstance(rng, torch.Generator):
        rng.set_state(state.cpu())


def read_checkpoint(path: str | os.PathLike, *, what: str = "", map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)`` with clear errors: ``FileNotFoundError`` for a
    missing file, ``ValueError`` for a truncated, corrupt or non-``weights_only`` one (``what``
    names the checkpoint in both messages, e.g. ``"diffuser"``)."""
    path = Path(path)
    label = f"{what} checkpoint" if what else "checkpoint"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no {label}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # truncated / corrupt / foreign pickle
        raise ValueError(f"{path}: corrupt or unreadable {label} ({type(err).__name__}: {err})") from err


def save_trajectories(
    td: TensorDictBase,
    path: str | os.PathLike,
    *,
    meta: dict | None = None,
    per_trajectory: TensorDictBase | None = None,
) -> Path:
    """Persist a trajectory batch as a memmap folder plus ``meta.json``, atomically.

    The folder is written under a temporary name and renamed at the end, so an interrupted
    write never leaves a directory that :func:`load_trajectories` accepts.

    Args:
        td: ``[N, H]`` trajectory batch (validated first).
        path: target directory (replaced if it exists).
        meta: JSON-serialisable metadata (env id, generator config, seed, ...).
        per_trajectory: optional ``[N]`` TensorDict (e.g. ``group`` ids) saved beside it.
    """
    validate_trajectories(td, name=str(path))
    path = Path(path)
    with atomic_directory(path) as tmp:
        td.memmap(tmp / "data")
        if per_trajectory is not None:
            if per_trajectory.batch_size != td.batch_size[:1]:
                raise ValueError(
                    f"{path}: per_trajectory batch_size {list(per_trajectory.batch_size)} "
                    f"!= [{td.batch_size[0]}]"
                )
            per_trajectory.memmap(tmp / "per_trajectory")
        full_meta = {
            "format_version": FORMAT_VERSION,
            "num_trajectories": int(td.batch_size[0]),
            "horizon": int(td.batch_size[1]),
            "obs_dim": int(td.get("observation").shape[-1]),
            "action_dim": int(td.get("action").shape[-1]),
            "num_transitions": int(td.get("mask").sum()),
            **(meta or {}),
        }
        # meta.json is written last: its presence marks a complete dataset
        atomic_write_text(tmp / "meta.json", json.dumps(full_meta, indent=2, default=str))
    return path


def read_memmap_folder(path: str | os.PathLike, *, what: str, format_version: int) -> tuple[TensorDict, dict]:
    """Read a folder written as ``data/`` (``TensorDict.memmap``) + ``meta.json`` (into memory).

    Shared by datasets and label sets; ``meta.json`` is written last, so its absence means
    an incomplete write.

    Raises:
        FileNotFoundError: ``meta.json`` or ``data/`` missing (``what`` names the kind of folder).
        ValueError: corrupt ``meta.json`` or a ``format_version`` other than ``format_version``.
    """
    path = Path(path)
    meta_file = path / "meta.json"
    if not meta_file.is_file() or not (path / "data").is_dir():
        raise FileNotFoundError(f"{path}: not a torchrl_ftb {what} (missing meta.json or data/)")
    try:
        meta = json.loads(meta_file.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{meta_file}: corrupt metadata ({err})") from err
    if meta.get("format_version") != format_version:
        raise ValueError(
            f"{meta_file}: format_version {meta.get('format_version')!r} is not supported "
            f"(expected {format_version})"
        )
    return TensorDict.load_memmap(path / "data").to_tensordict(), meta


def load_trajectories(
    path: str | os.PathLike, *, with_per_trajectory: bool = False
) -> tuple[TensorDict, dict] | tuple[TensorDict, dict, TensorDict | None]:
    """Load a dataset written by :func:`save_trajectories` (into memory) and check it.

    Returns:
        ``(td, meta)`` or, with ``with_per_trajectory=True``, ``(td, meta, per_traj_or_None)``.

    Raises:
        FileNotFoundError: no complete dataset at ``path``.
        ValueError: unknown format version or malformed content.
    """
    path = Path(path)
    td, meta = read_memmap_folder(path, what="dataset", format_version=FORMAT_VERSION)
    validate_trajectories(
        td, name=str(path), obs_dim=meta.get("obs_dim"), action_dim=meta.get("action_dim")
    )
    if not with_per_trajectory:
        return td, meta
    per = None
    if (path / "per_trajectory").exists():
        per = TensorDict.load_memmap(path / "per_trajectory").to_tensordict()
    return td, meta, per


def observation_statistics(observation: torch.Tensor, *, eps: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-dimension mean and standard deviation floored at ``eps``, of observations ``[T, obs_dim]``.

    The one observation z-score of the package (score model, BC actor, baselines). The floor
    keeps constant dimensions (e.g. Meta-World's zero-padded slots) finite; a floor rather than
    ``std + eps`` keeps ``(obs - loc) / scale`` invariant to the observations' units.

    Example:
        >>> loc, scale = observation_statistics(torch.tensor([[0.0, 1.0], [2.0, 1.0]]))
        >>> loc.tolist(), [round(v, 3) for v in scale.tolist()]
        ([1.0, 1.0], [1.0, 0.001])
    """
    if observation.ndim != 2 or observation.shape[0] < 1:
        raise ValueError(f"observation_statistics: expected [T, obs_dim] with T >= 1, got {list(observation.shape)}")
    observation = observation.float()
    if not bool(torch.isfinite(observation).all()):
        raise ValueError("observation_statistics: observations contain NaN or inf")
    std = observation.std(0, unbiased=False) if observation.shape[0] > 1 else torch.zeros_like(observation[0])
    return observation.mean(0), std.clamp_min(eps)
