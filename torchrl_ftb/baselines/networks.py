"""Actor / critic networks of the offline-RL baselines, built from torchrl modules.

Mirrors ``sota-implementations/iql/utils.py`` and ``td3_bc/utils.py`` of TorchRL 0.14:
``MLP`` bodies, a ``ProbabilisticActor`` with a ``TanhNormal`` head for IQL, a
``TanhModule``-squashed deterministic actor for TD3+BC, and ``ValueOperator`` critics.
The one difference: every network starts with the project's
:class:`~torchrl_ftb.policy.actor.ObservationNormalizer` (dataset z-score as buffers), so a
trained actor reads raw environment observations — the same convention as the BC actor.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_ftb.baselines import make_iql_model
    >>> actor, qvalue, value = make_iql_model(3, 2, hidden=(16, 16))
    >>> td = TensorDict({"observation": torch.randn(4, 3), "action": torch.rand(4, 2) * 2 - 1}, [4])
    >>> actor(td)["action"].shape, qvalue(td)["state_action_value"].shape, value(td)["state_value"].shape
    (torch.Size([4, 2]), torch.Size([4, 1]), torch.Size([4, 1]))
"""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from tensordict.nn.distributions import NormalParamExtractor
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator

from torchrl_ftb.policy.actor import ObservationNormalizer

__all__ = ["NormalizedMLP", "make_iql_model", "make_td3bc_model", "action_spec"]


class NormalizedMLP(nn.Module):
    """``MLP(normalize(observation), *other_inputs)`` — an ``MLP`` behind an observation z-score.

    TorchRL's ``MLP`` concatenates its positional inputs, so the same class serves the
    actor (``observation``) and the critics (``observation, action``).
    """

    def __init__(self, normalizer: ObservationNormalizer, mlp: nn.Module, head: nn.Module | None = None):
        super().__init__()
        self.normalizer = normalizer
        self.mlp = mlp
        self.head = head if head is not None else nn.Identity()

    def forward(self, observation: torch.Tensor, *others: torch.Tensor):
        return self.head(self.mlp(self.normalizer(observation), *others))


def action_spec(action_dim: int, *, device: torch.device | str | None = None) -> Bounded:
    """The ``Bounded(-1, 1)`` action spec every baseline assumes (Meta-World, MuJoCo, toy)."""
    return Bounded(-torch.ones(action_dim), torch.ones(action_dim), shape=(action_dim,), device=device)


def _normalizer(obs_dim: int, obs_loc, obs_scale) -> ObservationNormalizer:
    loc = torch.zeros(obs_dim) if obs_loc is None else torch.as_tensor(obs_loc, dtype=torch.float32).reshape(-1)
    scale = torch.ones(obs_dim) if obs_scale is None else torch.as_tensor(obs_scale, dtype=torch.float32).reshape(-1)
    if loc.numel() != obs_dim or scale.numel() != obs_dim:
        raise ValueError(f"obs_loc/obs_scale have {loc.numel()}/{scale.numel()} entries, obs_dim is {obs_dim}")
    return ObservationNormalizer(loc, scale)


def _mlp(in_features: int, out_features: int, hidden: Sequence[int]) -> MLP:
    return MLP(in_features=in_features, out_features=out_features, num_cells=list(hidden), activation_class=nn.ReLU)


def make_iql_model(
    obs_dim: int,
    action_dim: int,
    *,
    hidden: Sequence[int] = (256, 256),
    obs_loc: torch.Tensor | None = None,
    obs_scale: torch.Tensor | None = None,
    default_policy_scale: float = 1.0,
    scale_lb: float = 0.1,
    device: torch.device | str | None = None,
) -> nn.ModuleList:
    """IQL's actor, Q-network and state-value network (TorchRL's offline IQL recipe).

    Args:
        obs_dim: observation size.
        action_dim: action size (actions in ``[-1, 1]``).
        hidden: hidden widths of every MLP (ReLU).
        obs_loc: observation mean for the input z-score (default 0).
        obs_scale: observation scale (default 1).
        default_policy_scale: ``biased_softplus`` bias of the policy scale.
        scale_lb: lower bound of the policy scale.
        device: where the parameters live.

    Returns:
        ``ModuleList([actor, qvalue, value])``: ``actor`` is a ``ProbabilisticActor``
        (``TanhNormal``, deterministic mode = tanh of the mean) reading ``"observation"``;
        ``qvalue`` writes ``"state_action_value"``; ``value`` writes ``"state_value"``.
    """
    spec = action_spec(action_dim)
    actor_net = NormalizedMLP(
        _normalizer(obs_dim, obs_loc, obs_scale),
        _mlp(obs_dim, 2 * action_dim, hidden),
        NormalParamExtractor(scale_mapping=f"biased_softplus_{default_policy_scale}", scale_lb=scale_lb),
    )
    actor = ProbabilisticActor(
        module=TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
        default_interaction_type=ExplorationType.DETERMINISTIC,
    )
    qvalue = ValueOperator(
        NormalizedMLP(_normalizer(obs_dim, obs_loc, obs_scale), _mlp(obs_dim + action_dim, 1, hidden)),
        in_keys=["observation", "action"],
        out_keys=["state_action_value"],
    )
    value = ValueOperator(
        NormalizedMLP(_normalizer(obs_dim, obs_loc, obs_scale), _mlp(obs_dim, 1, hidden)),
        in_keys=["observation"],
        out_keys=["state_value"],
    )
    model = nn.ModuleList([actor, qvalue, value])
    return model.to(device) if device is not None else model


def make_td3bc_model(
    obs_dim: int,
    action_dim: int,
    *,
    hidden: Sequence[int] = (256, 256),
    obs_loc: torch.Tensor | None = None,
    obs_scale: torch.Tensor | None = None,
    device: torch.device | str | None = None,
) -> nn.ModuleList:
    """TD3+BC's deterministic actor and Q-network (TorchRL's td3_bc recipe).

    Returns:
        ``ModuleList([actor, qvalue])``: ``actor`` is ``TensorDictSequential(MLP → TanhModule)``
        writing ``"action"`` in ``[-1, 1]``; ``qvalue`` writes ``"state_action_value"``.
    """
    spec = action_spec(action_dim)
    actor = TensorDictSequential(
        TensorDictModule(
            NormalizedMLP(_normalizer(obs_dim, obs_loc, obs_scale), _mlp(obs_dim, action_dim, hidden)),
            in_keys=["observation"],
            out_keys=["param"],
        ),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
    )
    qvalue = ValueOperator(
        NormalizedMLP(_normalizer(obs_dim, obs_loc, obs_scale), _mlp(obs_dim + action_dim, 1, hidden)),
        in_keys=["observation", "action"],
        out_keys=["state_action_value"],
    )
    model = nn.ModuleList([actor, qvalue])
    return model.to(device) if device is not None else model

