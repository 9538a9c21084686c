"""Deterministic MLP actor for behaviour cloning (paper App. B.4: obs → 256 → 256 → act, ReLU).

The actor is a :class:`torchrl.modules.Actor` (a ``TensorDictModule`` reading
``"observation"`` and writing ``"action"``) wrapping an observation normaliser (z-score,
statistics stored as buffers so they travel with ``state_dict``), a
:class:`torchrl.modules.MLP` and a squashing of the output to ``[-1, 1]``.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_ftb.policy import make_bc_actor
    >>> actor = make_bc_actor(3, 2, hidden=(32, 32))
    >>> td = actor(TensorDict({"observation": torch.randn(5, 3)}, [5]))
    >>> td["action"].shape, bool(td["action"].abs().max() <= 1)
    (torch.Size([5, 2]), True)
"""
from __future__ import annotations

from typing import Literal, Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, Actor

from torchrl_ftb.data.trajectories import observation_statistics  # re-exported (one home: data)

__all__ = ["ObservationNormalizer", "SquashedMLP", "make_bc_actor", "make_bc_actor_for", "observation_statistics"]


class ObservationNormalizer(nn.Module):
    """``(obs - loc) / scale`` with ``loc``/``scale`` as buffers (saved in ``state_dict``)."""

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor):
        super().__init__()
        if loc.shape != scale.shape or loc.ndim != 1:
            raise ValueError(f"ObservationNormalizer: loc {list(loc.shape)} and scale {list(scale.shape)} must be equal 1-D")
        if not bool((scale > 0).all()):
            raise ValueError("ObservationNormalizer: scale must be > 0 in every dimension")
        self.register_buffer("loc", loc.detach().float().clone())
        self.register_buffer("scale", scale.detach().float().clone())

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return (observation - self.loc) / self.scale


class SquashedMLP(nn.Module):
    """Normalise observations, apply an MLP, squash to ``[-1, 1]`` (``tanh`` or clipping).

    ``tanh`` is the default: clipping (the authors' choice) has zero gradient once the
    pre-activation leaves ``[-1, 1]``, which can freeze a unit on a wrong side under MSE.
    """

    def __init__(self, normalizer: ObservationNormalizer, mlp: nn.Module, *, squash: str = "tanh"):
        super().__init__()
        if squash not in ("tanh", "clip"):
            raise ValueError(f"squash must be 'tanh' or 'clip', got {squash!r}")
        self.normalizer = normalizer
        self.mlp = mlp
        self.squash = squash

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        out = self.mlp(self.normalizer(observation))
        return torch.tanh(out) if self.squash == "tanh" else out.clamp(-1.0, 1.0)


def make_bc_actor(
    obs_dim: int,
    action_dim: int,
    *,
    hidden: Sequence[int] = (256, 256),
    obs_loc: torch.Tensor | None = None,
    obs_scale: torch.Tensor | None = None,
    squash: Literal["tanh", "clip"] = "tanh",
    device: torch.device | str | None = None,
) -> Actor:
    """Build the deterministic BC actor ``"observation"`` → ``"action"`` in ``[-1, 1]``.

    Args:
        obs_dim: observation size.
        action_dim: action size (actions are assumed to live in ``[-1, 1]``).
        hidden: hidden layer widths (ReLU).
        obs_loc: per-dimension observation mean (default zeros).
        obs_scale: per-dimension observation scale (default ones); see
            :func:`observation_statistics`.
        squash: ``"tanh"`` (default) or ``"clip"`` (the authors' choice).
        device: where the parameters live.

    Returns:
        A :class:`torchrl.modules.Actor` with a ``Bounded(-1, 1)`` action spec.

    Example:
        >>> actor = make_bc_actor(4, 2, hidden=(8,), obs_loc=torch.zeros(4), obs_scale=torch.ones(4))
        >>> sorted(k for k in actor.state_dict() if "normalizer" in k)
        ['module.normalizer.loc', 'module.normalizer.scale']
    """
    if obs_dim < 1 or action_dim < 1:
        raise ValueError(f"make_bc_actor: obs_dim and action_dim must be >= 1, got {obs_dim}, {action_dim}")
    loc = torch.zeros(obs_dim) if obs_loc is None else torch.as_tensor(obs_loc, dtype=torch.float32).reshape(-1)
    scale = torch.ones(obs_dim) if obs_scale is None else torch.as_tensor(obs_scale, dtype=torch.float32).reshape(-1)
    if loc.numel() != obs_dim or scale.numel() != obs_dim:
        raise ValueError(
            f"make_bc_actor: obs_loc/obs_scale have {loc.numel()}/{scale.numel()} entries, obs_dim is {obs_dim}"
        )
    mlp = MLP(
        in_features=obs_dim,
        out_features=action_dim,
        num_cells=list(hidden),
        activation_class=nn.ReLU,
    )
    module = SquashedMLP(ObservationNormalizer(loc, scale), mlp, squash=squash)
    spec = Bounded(-torch.ones(action_dim), torch.ones(action_dim), shape=(action_dim,))
    actor = Actor(module, in_keys=["observation"], out_keys=["action"], spec=spec)
    return actor.to(device) if device is not None else actor


def make_bc_actor_for(
    transitions: TensorDictBase,
    *,
    hidden: Sequence[int] = (256, 256),
    statistics_from: TensorDictBase | None = None,
    squash: Literal["tanh", "clip"] = "tanh",
    device: torch.device | str | None = None,
) -> Actor:
    """A :func:`make_bc_actor` sized for a flat transition set ``[T]`` and z-scoring its observations.

    Args:
        transitions: flat ``[T]`` TensorDict with ``observation`` and ``action`` (what BC trains on).
        hidden: hidden layer widths (ReLU).
        statistics_from: flat ``[T']`` TensorDict whose observations give the z-score instead
            (default: ``transitions``' own, as FTB and the BC baselines do).
        squash: ``"tanh"`` (default) or ``"clip"``.
        device: where the parameters live.

    Example:
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"observation": torch.randn(10, 3), "action": torch.zeros(10, 2)}, [10])
        >>> actor = make_bc_actor_for(data, hidden=(8,))
        >>> bool(torch.allclose(actor.module.normalizer.loc, data["observation"].mean(0)))
        True
    """
    for name, td in (("transitions", transitions), ("statistics_from", statistics_from)):
        if td is not None and ("observation" not in td.keys() or td.ndim != 1):
            raise ValueError(f"make_bc_actor_for: {name} must be a flat [T] TensorDict with 'observation', "
                             f"got batch size {list(td.batch_size)} and keys {sorted(map(str, td.keys()))}")
    if "action" not in transitions.keys():
        raise ValueError("make_bc_actor_for: transitions have no 'action'")
    source = transitions if statistics_from is None else statistics_from
    loc, scale = observation_statistics(source.get("observation"))
    return make_bc_actor(transitions.get("observation").shape[-1], transitions.get("action").shape[-1], hidden=hidden,
                         obs_loc=loc, obs_scale=scale, squash=squash, device=device)
