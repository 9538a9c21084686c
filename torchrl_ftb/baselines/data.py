"""Offline data for the baselines: transition replay buffers and sample-time reward relabelling.

Every baseline sees the *same* trajectory batch (docs/conventions.md) as FTB; this module
turns it into what each method consumes:

* :func:`make_offline_buffer` — valid steps as flat transitions in a seeded torchrl
  replay buffer, with optional replay-buffer transforms.
* :func:`make_reward_transforms` — the relabelling pattern users copy: a torchrl
  ``ModuleTransform`` that runs a reward ``TensorDictModule`` (``observation, action →
  ("next", "reward")``) on every sampled batch, followed by torchrl's ``RewardScaling``
  with statistics computed once on the whole dataset. Used for IQL + r_ψ, OPRL and the
  zero-reward sanity check (:func:`zero_reward_module`). Without a module it only rescales
  the true reward.
* :func:`select_top_trajectories` — the 10%BC selection (by true return or by a learned score).

Example:
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> from torchrl_ftb.baselines import make_offline_buffer, make_reward_transforms, zero_reward_module
    >>> trajs = make_toy_dataset(num_trajectories=8, horizon=16, seed=0)
    >>> rb = make_offline_buffer(trajs, batch_size=4, seed=0,
    ...                          transforms=make_reward_transforms(trajs, reward_module=zero_reward_module()))
    >>> batch = rb.sample()
    >>> batch.batch_size, float(batch["next", "reward"].abs().sum())
    (torch.Size([4]), 0.0)
"""
from __future__ import annotations

import math
from typing import Literal, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.data import ReplayBuffer
from torchrl.envs.transforms import ModuleTransform, RewardScaling, Transform

from torchrl_ftb.data import REWARD_KEY, TERMINATED_KEY, trajectories_to_flat, validate_trajectories
from torchrl_ftb.policy import make_transition_buffer

__all__ = [
    "REWARD_KEY",
    "TRANSITION_KEYS",
    "make_offline_buffer",
    "make_reward_transforms",
    "reward_scale",
    "relabel_rewards",
    "zero_reward_module",
    "select_top_trajectories",
]

#: what an actor-critic update reads (the reward may come from a transform instead)
TRANSITION_KEYS: tuple = ("observation", "action", ("next", "observation"), ("next", "done"), TERMINATED_KEY)

RewardNormalization = Literal["none", "return_range", "standardize"]


def make_offline_buffer(
    trajs: TensorDictBase,
    *,
    batch_size: int,
    seed: int = 0,
    transforms: Sequence[Transform] = (),
    require_reward: bool = False,
    device: torch.device | str | None = None,
    name: str = "dataset",
) -> ReplayBuffer:
    """Flat transitions of a trajectory batch in a seeded replay buffer, with transforms.

    The buffer itself is the policy stage's
    :func:`~torchrl_ftb.policy.make_transition_buffer` (one home for it), here keeping the
    keys an actor-critic update reads (:data:`TRANSITION_KEYS` + the reward if present).

    Args:
        trajs: ``[N, H]`` trajectory batch with ``mask``.
        batch_size: transitions per ``sample()``.
        seed: seeds the buffer's own ``torch.Generator`` (sampling is reproducible).
        transforms: replay-buffer transforms appended in order (run at ``sample()``).
        require_reward: raise if the data has no ``("next", "reward")``.
        device: storage device (default CPU).
        name: how to call the data in error messages.

    Raises:
        ValueError: malformed batch or a missing transition key.
    """
    validate_trajectories(trajs, name=name, require=[k for k in TRANSITION_KEYS if k not in ("observation", "action")])
    if require_reward and REWARD_KEY not in trajs.keys(True):
        raise ValueError(f"{name}: this method needs the true reward ('next', 'reward'), which the data lacks")
    flat = trajectories_to_flat(trajs)
    keys = tuple(k for k in (*TRANSITION_KEYS, REWARD_KEY) if k in flat.keys(True))
    rb = make_transition_buffer(flat, batch_size=int(batch_size), seed=int(seed), keys=keys, device=device)
    for t in transforms:
        rb.append_transform(t)
    return rb


@torch.no_grad()
def relabel_rewards(
    trajs: TensorDictBase, reward_module: TensorDictModuleBase, *, batch_size: int = 65536
) -> torch.Tensor:
    """Rewards ``[N, H, 1]`` that ``reward_module`` gives the valid steps of ``trajs`` (0 on padding)."""
    flat = trajectories_to_flat(trajs).select("observation", "action")
    param = next(iter(reward_module.parameters()), None)
    device = param.device if param is not None else flat.device
    out = []
    for start in range(0, flat.batch_size[0], batch_size):
        chunk = reward_module(flat[start : start + batch_size].to(device))
        out.append(chunk.get(REWARD_KEY).reshape(-1, 1).float().to(flat.device))
    rewards = torch.cat(out, 0)
    if not bool(torch.isfinite(rewards).all()):
        raise ValueError("relabel_rewards: the reward module produced NaN/inf rewards")
    mask = trajs.get("mask")
    full = torch.zeros(*mask.shape, 1, dtype=torch.float32, device=rewards.device)
    full[mask] = rewards
    return full


def reward_scale(
    rewards: torch.Tensor, mask: torch.Tensor, *, mode: RewardNormalization, target_range: float = 1000.0
) -> tuple[float, float]:
    """``(loc, scale)`` so that ``reward * scale + loc`` is normalised as ``mode`` says.

    * ``"none"``: ``(0, 1)``.
    * ``"return_range"`` (IQL's locomotion choice, Kostrikov et al. 2022): scale by
      ``target_range / (max_return - min_return)`` over the dataset trajectories, no shift.
    * ``"standardize"``: per-transition z-score over valid steps.

    A constant reward (e.g. all zero) keeps scale 1 instead of dividing by zero.

    Example:
        >>> r = torch.tensor([[[1.0], [1.0]], [[0.0], [0.0]]])
        >>> reward_scale(r, torch.ones(2, 2, dtype=torch.bool), mode="return_range", target_range=1.0)
        (0.0, 0.5)
    """
    if mode == "none":
        return 0.0, 1.0
    valid = rewards.squeeze(-1)[mask]
    if mode == "return_range":
        returns = (rewards.squeeze(-1) * mask).sum(-1)
        spread = float(returns.max() - returns.min())
        return 0.0, (target_range / spread) if spread > 1e-8 else 1.0
    if mode == "standardize":
        std = float(valid.std(unbiased=False)) if valid.numel() > 1 else 0.0
        scale = 1.0 / std if std > 1e-8 else 1.0
        return -float(valid.mean()) * scale, scale
    raise ValueError(f"reward normalization must be 'none', 'return_range' or 'standardize', got {mode!r}")


def make_reward_transforms(
    trajs: TensorDictBase,
    *,
    reward_module: TensorDictModuleBase | None = None,
    normalization: RewardNormalization = "none",
    target_range: float = 1000.0,
) -> list[Transform]:
    """Replay-buffer transforms giving each sampled transition the reward a method trains on.

    Args:
        trajs: the trajectory batch the buffer holds (normalisation statistics come from it).
        reward_module: ``observation, action → ("next", "reward")`` module (e.g. a learned
            r_ψ, an ensemble mean, :func:`zero_reward_module`); ``None`` keeps the true reward.
        normalization: see :func:`reward_scale`; statistics are computed once on the rewards
            the agent will see (the relabelled ones when ``reward_module`` is given).
        target_range: return spread for ``"return_range"``.

    Returns:
        ``[ModuleTransform(reward_module, no_grad=True)]`` (if a module is given) followed by
        ``RewardScaling(loc, scale)`` on ``("next", "reward")`` (if the normalisation is not
        the identity).
    """
    transforms: list[Transform] = []
    if reward_module is not None:
        transforms.append(ModuleTransform(module=reward_module, no_grad=True))
        rewards = relabel_rewards(trajs, reward_module)
    elif REWARD_KEY in trajs.keys(True):
        rewards = trajs.get(REWARD_KEY).float()
    else:
        raise ValueError("make_reward_transforms: data has no ('next', 'reward') and no reward_module was given")
    loc, scale = reward_scale(rewards, trajs.get("mask"), mode=normalization, target_range=target_range)
    if (loc, scale) != (0.0, 1.0):
        transforms.append(RewardScaling(loc=loc, scale=scale, in_keys=[REWARD_KEY]))
    return transforms


def _zero_reward(observation: torch.Tensor) -> torch.Tensor:
    return torch.zeros(*observation.shape[:-1], 1, dtype=torch.float32, device=observation.device)


def zero_reward_module() -> TensorDictModule:
    """A reward module writing ``("next", "reward") = 0`` (the IQL sanity-check baseline)."""
    return TensorDictModule(_zero_reward, in_keys=["observation"], out_keys=[REWARD_KEY])


def select_top_trajectories(
    trajs: TensorDictBase, values: torch.Tensor, *, fraction: float = 0.1
) -> tuple[TensorDictBase, torch.Tensor]:
    """The top ``fraction`` of trajectories by ``values`` (10%BC), at least one.

    Args:
        trajs: ``[N, H]`` batch.
        values: ``[N]`` ranking values (true return, or a learned score).
        fraction: share kept, in ``(0, 1]``; ``ceil(fraction * N)`` trajectories.

    Returns:
        ``(selected [k, H], indices [k])``, best first.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=10, horizon=4)
        >>> _, idx = select_top_trajectories(trajs, torch.arange(10.0), fraction=0.2)
        >>> idx.tolist()
        [9, 8]
    """
    n = trajs.batch_size[0]
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"select_top_trajectories: fraction must be in (0, 1], got {fraction}")
    values = torch.as_tensor(values).reshape(-1)
    if values.numel() != n:
        raise ValueError(f"select_top_trajectories: {values.numel()} values for {n} trajectories")
    if not bool(torch.isfinite(values).all()):
        raise ValueError("select_top_trajectories: ranking values contain NaN/inf")
    k = max(1, math.ceil(fraction * n - 1e-9))
    idx = torch.argsort(values.float(), descending=True, stable=True)[:k]
    return trajs[idx], idx
