"""Behaviour cloning of flat ``(s, a)`` transitions (paper Alg. 4 lines 15–19, Table 6).

The loss is torchrl's :class:`~torchrl.objectives.BCLoss` with ``loss_function="mse"`` (the
deterministic-actor MSE of Alg. 4), sampled from a torchrl ``ReplayBuffer``. Training can
checkpoint periodically and resume from the last checkpoint.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_ftb.policy import make_bc_actor, train_bc
    >>> obs = torch.randn(256, 3)
    >>> data = TensorDict({"observation": obs, "action": obs[:, :2].tanh()}, [256])
    >>> actor = make_bc_actor(3, 2, hidden=(32,))
    >>> out = train_bc(actor, data, steps=20, batch_size=64, lr=1e-3, progress=False)
    >>> out["steps"]
    20
"""
from __future__ import annotations

import numbers
import os
import warnings
from pathlib import Path
from typing import Any, Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from torchrl.objectives import BCLoss
from tqdm.auto import tqdm

from torchrl_ftb.data import atomic_torch_save, restore_sampler_rng, sampler_rng_state

__all__ = ["make_transition_buffer", "train_bc", "load_bc_checkpoint"]

_CKPT_KIND = "torchrl_ftb.bc"


def make_transition_buffer(
    transitions: TensorDictBase,
    *,
    batch_size: int,
    seed: int = 0,
    keys: tuple = ("observation", "action"),
    device: torch.device | str | None = None,
) -> ReplayBuffer:
    """A uniformly-sampled ``ReplayBuffer`` over flat transitions ``[T]`` (only ``keys`` kept).

    Raises:
        ValueError: not a flat ``[T]`` TensorDict, empty, or missing a key.
    """
    if not isinstance(transitions, TensorDictBase) or transitions.batch_dims != 1:
        shape = list(transitions.batch_size) if isinstance(transitions, TensorDictBase) else type(transitions)
        raise ValueError(f"transitions: expected a flat TensorDict with batch_size [T], got {shape}")
    if transitions.numel() == 0:
        raise ValueError("transitions: empty (0 transitions)")
    for key in keys:
        if key not in transitions.keys(True):
            raise ValueError(f"transitions: missing key {key!r}")
    data = transitions.select(*keys)
    generator = torch.Generator().manual_seed(int(seed))
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(data.numel(), device=device if device is not None else "cpu"),
        sampler=RandomSampler(),
        batch_size=batch_size,
        generator=generator,
    )
    buffer.extend(data)
    return buffer


def load_bc_checkpoint(path: str | os.PathLike, actor: TensorDictModule) -> dict[str, Any]:
    """Load a :func:`train_bc` checkpoint into ``actor`` and return the raw checkpoint dict.

    Raises:
        ValueError: unreadable file, not a BC checkpoint, or weights that do not fit ``actor``.
    """
    path = Path(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as err:  # corrupt / truncated file
        raise ValueError(f"{path}: corrupt or unreadable BC checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(ckpt, dict) or ckpt.get("kind") != _CKPT_KIND:
        raise ValueError(f"{path}: not a torchrl_ftb BC checkpoint")
    try:
        actor.load_state_dict(ckpt["actor"])
    except (RuntimeError, KeyError) as err:
        raise ValueError(f"{path}: checkpoint does not match the actor ({err})") from err
    return ckpt


def check_number(owner: str, name: str, value, *, whole: bool = False) -> None:
    """Refuse a non-number (a string, a bool, ``None``) before a range check would raise a bare ``TypeError``;
    with ``whole``, a count that is not a whole number (``500.0`` is 500, ``10.5`` is refused, not cut to 10).

    Example:
        >>> check_number("train_bc", "steps", 100.0, whole=True)
        >>> check_number("train_bc", "steps", "many")
        Traceback (most recent call last):
        ...
        ValueError: train_bc: steps must be a number, got 'many'
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):  # numpy's numbers too
        raise ValueError(f"{owner}: {name} must be a number, got {value!r}")
    if whole and not float(value).is_integer():  # inf and nan too
        raise ValueError(f"{owner}: {name} must be a whole number, got {value!r}")


def check_bc_options(*, steps: int, batch_size: int = 1024, lr: float = 1e-4, weight_decay: float = 1e-3) -> None:
    """Check :func:`train_bc`'s numbers (same names and defaults) without training.

    A recipe calls it before any training, so a bad BC option fails in seconds instead of after the
    score model's and the diffuser's training; :func:`train_bc` calls it too.

    Raises:
        ValueError: naming the first option out of range.

    Example:
        >>> check_bc_options(steps=10_000, batch_size=1024, lr=1e-4, weight_decay=1e-3)
        >>> check_bc_options(steps=100, lr=0.0)
        Traceback (most recent call last):
        ...
        ValueError: train_bc: lr must be > 0, got 0.0
    """
    for name, value in (("steps", steps), ("batch_size", batch_size), ("lr", lr), ("weight_decay", weight_decay)):
        check_number("train_bc", name, value, whole=name in ("steps", "batch_size"))
    if steps < 0:
        raise ValueError(f"train_bc: steps must be >= 0, got {steps}")
    if batch_size < 1:
        raise ValueError(f"train_bc: batch_size must be >= 1, got {batch_size}")
    if not lr > 0:
        raise ValueError(f"train_bc: lr must be > 0, got {lr}")
    if not weight_decay >= 0:
        raise ValueError(f"train_bc: weight_decay must be >= 0, got {weight_decay}")


def train_bc(
    actor: TensorDictModule,
    transitions: TensorDictBase | ReplayBuffer,
    *,
    steps: int,
    batch_size: int = 1024,
    lr: float = 1e-4,
    weight_decay: float = 1e-3,
    seed: int = 0,
    logger: Any | None = None,
    log_every: int = 100,
    progress: bool = True,
    device: torch.device | str | None = None,
    checkpoint_path: str | os.PathLike | None = None,
    checkpoint_every: int = 0,
    resume: bool = False,
    eval_fn: Callable[[int], dict[str, float]] | None = None,
    eval_every: int = 0,
) -> dict[str, Any]:
    """Train ``actor`` by MSE behaviour cloning (torchrl ``BCLoss``) with Adam + L2 weight decay.

    Args:
        actor: deterministic actor ``"observation"`` → ``"action"`` (e.g. :func:`make_bc_actor`);
            trained in place.
        transitions: flat ``[T]`` TensorDict with ``observation``/``action`` or a ready
            ``ReplayBuffer`` yielding such batches.
        steps: total gradient steps (including those done before a resume).
        batch_size: batch size (Table 6 / App. B.4: 1024).
        lr: Adam learning rate (1e-4).
        weight_decay: Adam weight decay (Table 6: 1e-3 Meta-World, 2e-4 D4RL/NeoRL).
        seed: seeds the batch sampling (and torch's global RNG).
        logger: a ``torchrl.record.loggers`` logger (``log_scalar``), optional.
        log_every: log the mean loss every this many steps.
        progress: show a tqdm bar.
        device: training device (default: the actor's).
        checkpoint_path: where to write ``{actor, optimizer, step}`` (atomic).
        checkpoint_every: checkpoint every this many steps (0: only at the end).
        resume: continue from ``checkpoint_path`` if it exists.
        eval_fn: ``eval_fn(step) -> metrics`` called every ``eval_every`` steps and at the end.
        eval_every: evaluation period (0: only at the end, if ``eval_fn`` is given).

    Returns:
        ``{"steps", "loss" (mean of the last logging window), "start_step", "evaluations"}``.

    Raises:
        ValueError: bad arguments (:func:`check_bc_options`), or a checkpoint that is corrupt or does not fit
            the actor.
    """
    check_bc_options(steps=steps, batch_size=batch_size, lr=lr, weight_decay=weight_decay)
    steps, batch_size = int(steps), int(batch_size)  # whole numbers (checked); a config's 100.0 is 100
    torch.manual_seed(int(seed))
    if device is None:
        device = next(actor.parameters()).device
    device = torch.device(device)
    actor.to(device)
    buffer = (
        transitions
        if isinstance(transitions, ReplayBuffer)
        else make_transition_buffer(transitions, batch_size=batch_size, seed=seed)
    )
    with warnings.catch_warnings():  # torchrl's harmless "target_actor_network_params" annotation notice
        warnings.filterwarnings("ignore", message=".*target_actor_network_params.*")
        loss_module = BCLoss(actor, loss_function="mse")
    optimizer = torch.optim.Adam(actor.parameters(), lr=lr, weight_decay=weight_decay)

    start_step = 0
    if resume and checkpoint_path is not None and Path(checkpoint_path).exists():
        ckpt = load_bc_checkpoint(checkpoint_path, actor)
        try:
            optimizer.load_state_dict(ckpt["optimizer"])
        except (ValueError, KeyError) as err:
            raise ValueError(f"{checkpoint_path}: optimizer state does not match ({err})") from err
        start_step = int(ckpt["step"])
        restore_sampler_rng(buffer, ckpt.get("sampler_rng"))

    def save(step: int) -> None:
        if checkpoint_path is None:
            return
        state = {"kind": _CKPT_KIND, "step": step, "actor": actor.state_dict(), "optimizer": optimizer.state_dict()}
        if (rng := sampler_rng_state(buffer)) is not None:
            state["sampler_rng"] = rng
        atomic_torch_save(state, checkpoint_path)

    evaluations: list[dict[str, float]] = []

    def evaluate(step: int) -> None:
        if eval_fn is None:
            return
        metrics = {k: float(v) for k, v in eval_fn(step).items() if v is not None}
        evaluations.append({"step": step, **metrics})
        if logger is not None:
            for k, v in metrics.items():
                logger.log_scalar(f"bc_eval/{k}", v, step=step)

    actor.train()
    window: list[float] = []
    last_loss = float("nan")
    bar = tqdm(range(start_step, steps), desc="BC", disable=not progress, initial=start_step, total=steps)
    for step in bar:
        batch = buffer.sample().to(device)
        loss = loss_module(batch)["loss_bc"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        window.append(float(loss.detach()))
        done = step + 1
        if done % max(log_every, 1) == 0 or done == steps:
            last_loss = sum(window) / len(window)
            window.clear()
            bar.set_postfix(loss=f"{last_loss:.4f}")
            if logger is not None:
                logger.log_scalar("bc/loss", last_loss, step=done)
        if checkpoint_every and done % checkpoint_every == 0 and done != steps:
            save(done)
        if eval_every and done % eval_every == 0 and done != steps:
            evaluate(done)
            actor.train()
    bar.close()
    save(steps)
    evaluate(steps)
    actor.eval()
    return {"steps": steps, "start_step": start_step, "loss": last_loss, "evaluations": evaluations}
