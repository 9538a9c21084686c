"""The trajectory score model ``s_psi`` of FTB (paper §3.2, App. B.2).

``s(tau) = sum_h gamma^h * r_psi(s_h, a_h) * mask_h``: an MLP reward ``r_psi`` applied per
step and summed over the valid steps of a padded trajectory batch ``[N, H]`` (+ ``"mask"``).
This is the *one* score definition of the project (blocks, flow filter, reports all use it).
``gamma`` (default 1.0) is stored in the model (a buffer, so it is saved in checkpoints).

``horizon`` (default ``None``: the paper's sum) is the stop-rule fill of the scripted teachers'
:func:`~torchrl_ftb.data.labels.true_return`: a trajectory of ``n < horizon`` valid steps whose
last step is not ``("next", "terminated")`` keeps earning its last step's ``r_psi`` until step
``horizon - 1``. On Meta-World a success ends the episode (a stop rule, not a terminal state)
while a failure runs the full 500 steps, so the plain sum lets a failure collect score by lasting
longer; with the fill every trajectory is scored over the same horizon. Where all trajectories
have ``horizon`` steps the two definitions agree.

The per-step reward is exposed as :attr:`ScoreModel.reward_module`, a
:class:`~tensordict.nn.TensorDictModule` ``(observation, action) -> ("next", "reward")`` for
relabelling flat transitions (e.g. IQL + ``r_psi``). With ``num_members > 1`` the reward is an
ensemble (:class:`~tensordict.nn.EnsembleModule`); the score and the reward are the ensemble
means, and the members' scores and their standard deviation are output too.

Example:
    >>> from torchrl_ftb.preference import ScoreModel
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=4, horizon=8, seed=0)
    >>> model = ScoreModel(3, 2, num_cells=16, seed=0)
    >>> model(trajs)["score"].shape
    torch.Size([4])
"""
from __future__ import annotations

import copy
import math
import os
from pathlib import Path
from typing import Any, Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import EnsembleModule, TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import MLP

from torchrl_ftb.data.trajectories import (
    atomic_torch_save, observation_statistics, read_checkpoint, stop_rule_fill,
)

__all__ = [
    "NORMALIZED_SCORE_KEY", "REWARD_ACTIVATIONS", "SCORE_MODEL_CHECKPOINT", "ScoreModel", "load_score_model",
    "normalized_scores", "save_score_model", "score_trajectories", "with_normalized_scores",
]

#: key of a trajectory's dataset-normalised score ``ŝ`` (:func:`normalized_scores`) in an ``[N, H]``
#: batch, stored per step (constant in time); what a ``score_condition`` diffuser reads
NORMALIZED_SCORE_KEY = "normalized_score"


def _prefixed(prefix: NestedKey | Sequence, key: NestedKey) -> NestedKey:
    """``prefix`` + ``key`` as one nested key (a plain string when the prefix is empty)."""
    prefix = (prefix,) if isinstance(prefix, str) else tuple(prefix)
    key = (key,) if isinstance(key, str) else tuple(key)
    full = (*prefix, *key)
    return full[0] if len(full) == 1 else full


def _suffixed(key: NestedKey, suffix: str) -> NestedKey:
    return f"{key}{suffix}" if isinstance(key, str) else (*key[:-1], f"{key[-1]}{suffix}")


#: output squashing of the per-step reward ``r_psi`` (``ScoreModel(reward_activation=...)``)
REWARD_ACTIVATIONS: dict[str, type[nn.Module]] = {"identity": nn.Identity, "sigmoid": nn.Sigmoid}


class _StepReward(nn.Module):
    """``(observation, action) -> r_psi`` per step; members ``[C, *B, 1]``, forward = member mean."""

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        num_cells: int,
        num_layers: int,
        activation_class: type[nn.Module],
        num_members: int,
        device: torch.device | str | None,
        reward_activation: str = "identity",
    ) -> None:
        super().__init__()
        if reward_activation not in REWARD_ACTIVATIONS:
            raise ValueError(f"ScoreModel: reward_activation must be one of {sorted(REWARD_ACTIVATIONS)}, "
                             f"got {reward_activation!r}")
        mlp = MLP(
            in_features=observation_dim + action_dim,
            out_features=1,
            num_cells=[num_cells] * (num_layers - 1),
            activation_class=activation_class,
            device=device,
        )
        # fixed internal keys: this td only lives inside _StepReward
        member = TensorDictModule(mlp, in_keys=["observation", "action"], out_keys=["reward"])
        self.num_members = num_members
        self.squash = REWARD_ACTIVATIONS[reward_activation]()  # applied to every member's output
        self.net = EnsembleModule(member, num_copies=num_members) if num_members > 1 else member
        self.observation_dim = observation_dim
        self.action_dim = action_dim
        # observation normaliser (identity until ScoreModel.fit_normalizer); saved with the model
        self.register_buffer("obs_loc", torch.zeros(observation_dim, device=device))
        self.register_buffer("obs_scale", torch.ones(observation_dim, device=device))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints written before the normaliser existed load as un-normalised models
        for name, fill in (("obs_loc", torch.zeros_like), ("obs_scale", torch.ones_like)):
            state_dict.setdefault(prefix + name, fill(getattr(self, name)))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def members(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        if observation.shape[-1] != self.observation_dim or action.shape[-1] != self.action_dim:
            raise ValueError(
                f"ScoreModel: expected observation dim {self.observation_dim} and action dim "
                f"{self.action_dim}, got {observation.shape[-1]} and {action.shape[-1]}"
            )
        dtype = next(self.parameters()).dtype  # e.g. float64 label files -> float32 weights
        observation = (observation.to(dtype) - self.obs_loc.to(dtype)) / self.obs_scale.to(dtype)
        td = TensorDict(
            {"observation": observation, "action": action.to(dtype)},
            batch_size=observation.shape[:-1],
        )
        if self.num_members == 1:
            raw = self.net(td).get("reward").unsqueeze(0)
        elif observation.device.type == "cpu":
            raw = self.members_sequential(td)
        else:
            raw = self.net(td).get("reward")
        return self.squash(raw)

    def members_sequential(self, td: TensorDictBase) -> torch.Tensor:
        """The ensemble's ``[C, ..., 1]`` rewards one member after another (same parameters and
        gradients as the ``EnsembleModule``'s ``torch.vmap`` call). Used on CPU, where vmap's
        batched matmul is the slower path: 3 members on 17k steps, forward + backward, 0.60 s
        sequential vs 0.87 s vmapped (1 thread, the other core busy; a whole Bradley-Terry step on
        30 button-press pairs 0.57 s vs 0.96 s). ``tests/test_preference.py`` checks they agree."""
        outs = []
        for params in self.net.params_td.unbind(0):
            with params.to_module(self.net.module):
                outs.append(self.net.module(td.clone(False)).get("reward"))
        return torch.stack(outs)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.members(observation, action).mean(0)


class ScoreModel(TensorDictModuleBase):
    """Trajectory score ``s(tau) = sum_h gamma^h r_psi(s_h, a_h) mask_h`` as a TensorDict module.

    Reads ``observation [*B, H, obs_dim]``, ``action [*B, H, act_dim]`` and ``mask [*B, H]``
    (under an optional nested ``prefix``) and writes ``"score" [*B]`` (with an ensemble also
    ``"score_members" [*B, C]`` and ``"score_std" [*B]``).

    * On a trajectory batch ``[N, H]`` (``batch_size`` equal to ``mask.shape``) an ``[N]``
      entry cannot be stored in the input, so :meth:`forward` returns a **new** ``[N]``
      TensorDict holding the outputs.
    * On a TensorDict whose batch is ``[*B]`` with the trajectories nested under ``prefix``
      (e.g. labels ``[M]`` with ``"tau0"`` ``[M, L]``) the outputs are written in place.
      Use :meth:`with_prefix` to get such a view sharing the parameters, or call
      :meth:`score` on any sub-TensorDict.

    ``r_psi`` reads the observation through a per-dimension normaliser ``(obs - loc) / scale``
    stored as buffers (identity by default; :meth:`fit_normalizer` fits it on a dataset's valid
    steps, so every caller — labels, blocks, flow filter, reward relabelling — sees the same
    function of the raw observation).

    Args:
        observation_dim: size of ``observation``.
        action_dim: size of ``action``.

    Keyword Args:
        num_cells: hidden width of the MLP (Table 4: 256).
        num_layers: number of linear layers (Table 4: 3).
        activation_class: hidden activation (Table 4: ReLU).
        gamma: discount of the per-step rewards in the score (default 1.0).
        reward_activation: squashing of the MLP output into ``r_psi``: ``"identity"`` (default,
            the paper's Eq. 4) or ``"sigmoid"`` (per-step reward in (0, 1), as the authors' code
            scores trajectories; the same ``r_psi`` is then trained, scored and relabelled with).
            Positive per-step rewards make a longer trajectory of equal per-step quality score
            higher, the prior of tasks whose rewards are positive (Meta-World, locomotion).
        num_members: ensemble size (1 = a single MLP).
        horizon: stop-rule fill (module docstring): score every full trajectory as if it lasted
            ``horizon`` steps, repeating its last step's ``r_psi``, unless that step is
            ``terminated_key``. A batch without ``terminated_key`` (e.g. the diffuser's samples)
            counts as never terminated, so use it only for tasks without terminal states
            (Meta-World), not where episodes end by falling (locomotion). ``None`` (default): the
            paper's sum over the valid steps.
        terminated_key: per-step termination flag read by ``horizon`` (relative to ``prefix``).
        prefix: nested key prefix under which the trajectories are read.
        observation_key, action_key, mask_key: entry names (relative to ``prefix``).
        score_key: output key for the score (at the root).
        device: parameter device.
        seed: seeds the parameter initialisation (the global RNG state is restored).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> model = ScoreModel(3, 2, num_cells=16, seed=0)
        >>> obs, act = torch.randn(5, 7, 3), torch.randn(5, 7, 2)
        >>> mask = torch.arange(7).expand(5, 7) < 4
        >>> labels = TensorDict({"tau0": TensorDict(
        ...     {"observation": obs, "action": act, "mask": mask}, [5, 7])}, [5])
        >>> model.with_prefix("tau0", score_key="score0")(labels)["score0"].shape
        torch.Size([5])
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        num_cells: int = 256,
        num_layers: int = 3,
        activation_class: type[nn.Module] = nn.ReLU,
        gamma: float = 1.0,
        reward_activation: str = "identity",
        num_members: int = 1,
        horizon: int | None = None,
        terminated_key: NestedKey = ("next", "terminated"),
        prefix: NestedKey | Sequence = (),
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        mask_key: NestedKey = "mask",
        score_key: NestedKey = "score",
        device: torch.device | str | None = None,
        seed: int | None = None,
    ) -> None:
        super().__init__()
        if num_layers < 1 or num_cells < 1 or num_members < 1:
            raise ValueError(
                f"ScoreModel: num_layers, num_cells and num_members must be >= 1, got "
                f"{num_layers}, {num_cells}, {num_members}"
            )
        if not 0.0 < float(gamma) <= 1.0:
            raise ValueError(f"ScoreModel: gamma must be in (0, 1], got {gamma}")
        if horizon is not None and int(horizon) < 1:
            raise ValueError(f"ScoreModel: horizon must be >= 1 or None, got {horizon}")
        self.horizon = None if horizon is None else int(horizon)
        self.terminated_key = terminated_key
        self.hparams = {
            "observation_dim": int(observation_dim), "action_dim": int(action_dim),
            "num_cells": int(num_cells), "num_layers": int(num_layers),
            "num_members": int(num_members), "gamma": float(gamma),
            "reward_activation": str(reward_activation), "horizon": self.horizon,
        }
        with torch.random.fork_rng(devices=[]):
            if seed is not None:
                torch.manual_seed(seed)
            step = _StepReward(
                observation_dim, action_dim, num_cells=num_cells, num_layers=num_layers,
                activation_class=activation_class, num_members=num_members, device=device,
                reward_activation=reward_activation,
            )
        self.reward_module = TensorDictModule(
            step, in_keys=[observation_key, action_key], out_keys=[("next", "reward")]
        )
        self.register_buffer("gamma", torch.tensor(float(gamma), device=device))
        self._set_keys(prefix, observation_key, action_key, mask_key, score_key)

    # -- keys ---------------------------------------------------------------------------
    def _set_keys(self, prefix, observation_key, action_key, mask_key, score_key) -> None:
        prefix = (prefix,) if isinstance(prefix, str) else tuple(prefix)
        self.prefix = prefix
        self._rel_keys = (observation_key, action_key, mask_key)
        self.score_key = score_key
        self.in_keys = [_prefixed(prefix, k) for k in self._rel_keys]
        outs = [score_key]
        if self.num_members > 1:
            outs += [_suffixed(score_key, "_members"), _suffixed(score_key, "_std")]
        self.out_keys = outs

    def with_prefix(self, prefix: NestedKey | Sequence, *, score_key: NestedKey = "score") -> "ScoreModel":
        """A view of this model reading trajectories under ``prefix``; shares all parameters.

        Example:
            >>> m = ScoreModel(3, 2, num_cells=8).with_prefix("tau1", score_key="score1")
            >>> m.in_keys[0]
            ('tau1', 'observation')
        """
        view = copy.copy(self)  # shallow: shares _modules/_parameters/_buffers with self
        view._set_keys(prefix, *self._rel_keys, score_key)
        return view

    @property
    def read_keys(self) -> tuple:
        """The trajectory keys :meth:`score` reads, relative to the prefix: observation, action, mask and, with
        ``horizon``, ``terminated_key`` (read where present). Select these, not fewer, before scoring a copy: a
        batch that lost the flag is filled as if never terminated (:meth:`_stop_rule_fill`)."""
        return self._rel_keys + ((self.terminated_key,) if self.horizon is not None else ())

    @property
    def num_members(self) -> int:
        return self.reward_module.module.num_members

    @property
    def normalizer_fitted(self) -> bool:
        """Whether the observation normaliser differs from the identity."""
        step = self.reward_module.module
        return bool(step.obs_loc.ne(0).any() or step.obs_scale.ne(1).any())

    @torch.no_grad()
    def fit_normalizer(self, trajs: TensorDictBase, *, eps: float = 1e-3) -> "ScoreModel":
        """Fit the observation normaliser on the valid steps of a trajectory batch; returns self.

        ``loc``/``scale`` are :func:`torchrl_ftb.data.observation_statistics` (mean and
        standard deviation floored at ``eps``, the statistics the BC actor uses: constant
        dimensions, e.g. Meta-World's zero slots, stay finite).
        Fit it on the *dataset* (not on the few labelled trajectories) before training.

        Example:
            >>> from torchrl_ftb.testing import make_toy_dataset
            >>> trajs = make_toy_dataset(num_trajectories=8, horizon=8, seed=0)
            >>> ScoreModel(3, 2, num_cells=8).fit_normalizer(trajs).normalizer_fitted
            True
        """
        obs_key, _, mask_key = self._rel_keys
        mask = trajs.get(mask_key)
        if mask.dtype != torch.bool or not bool(mask.any()):
            raise ValueError(f"ScoreModel.fit_normalizer: {mask_key!r} must be a bool mask with a valid step")
        obs = trajs.get(obs_key)[mask].float()
        step = self.reward_module.module
        if obs.shape[-1] != step.observation_dim:
            raise ValueError(f"ScoreModel.fit_normalizer: observation dim {obs.shape[-1]}, model expects "
                             f"{step.observation_dim}")
        if not bool(torch.isfinite(obs).all()):
            raise ValueError("ScoreModel.fit_normalizer: observations contain NaN or inf")
        loc, scale = observation_statistics(obs, eps=eps)
        step.obs_loc.copy_(loc)
        step.obs_scale.copy_(scale)
        return self

    # -- maths --------------------------------------------------------------------------
    def step_rewards(self, trajs: TensorDictBase) -> torch.Tensor:
        """Per-step rewards of every member, ``[C, *B, H]`` (padded steps included, not masked)."""
        obs_key, act_key, _ = self._rel_keys
        return self.reward_module.module.members(trajs.get(obs_key), trajs.get(act_key)).squeeze(-1)

    def discounts(self, horizon: int) -> torch.Tensor:
        """``gamma^h`` for ``h = 0..horizon-1``."""
        return self.gamma ** torch.arange(horizon, device=self.gamma.device, dtype=self.gamma.dtype)

    def score(self, trajs: TensorDictBase, *, members: bool = False) -> torch.Tensor:
        """Score of a trajectory (sub-)TensorDict: ``[*B]`` (ensemble mean) or ``[C, *B]``.

        Padded steps (``mask`` False) contribute exactly zero, whatever their content.
        """
        obs_key, act_key, mask_key = self._rel_keys
        mask = trajs.get(mask_key)
        if mask.dtype != torch.bool:
            raise ValueError(f"ScoreModel: {mask_key!r} must be bool, got {mask.dtype}")
        # r_psi is evaluated on the valid steps only (padding is never computed, so it
        # cannot leak in, and long-horizon padded data cost only their valid steps)
        where = mask.nonzero(as_tuple=True)
        rewards = self.reward_module.module.members(trajs.get(obs_key)[where], trajs.get(act_key)[where])
        discounted = rewards.squeeze(-1) * self.discounts(mask.shape[-1]).to(rewards.dtype)[where[-1]]
        batch = mask.shape[:-1]
        traj = torch.arange(batch.numel(), device=mask.device).reshape(batch)[where[:-1]]
        per_member = rewards.new_zeros(rewards.shape[0], batch.numel()).index_add(1, traj, discounted)
        per_member = per_member.reshape(rewards.shape[0], *batch)
        if self.horizon is not None:
            per_member = per_member + self._stop_rule_fill(trajs, mask)
        return per_member if members else per_member.mean(0)

    def _stop_rule_fill(self, trajs: TensorDictBase, mask: torch.Tensor) -> torch.Tensor:
        # r_psi of each trajectory's last valid step times its stop-rule weight, [C, *B]
        obs_key, act_key, _ = self._rel_keys
        keys = trajs.keys(include_nested=True, leaves_only=True)
        terminated = trajs.get(self.terminated_key) if self.terminated_key in keys else None
        last, weight = stop_rule_fill(mask, horizon=self.horizon, discount=float(self.gamma), terminated=terminated)
        index = last[..., None, None]
        obs, act = trajs.get(obs_key), trajs.get(act_key)
        obs = obs.gather(-2, index.expand(*last.shape, 1, obs.shape[-1])).squeeze(-2)
        act = act.gather(-2, index.expand(*last.shape, 1, act.shape[-1])).squeeze(-2)
        last_reward = self.reward_module.module.members(obs, act).squeeze(-1)  # [C, *B]
        return last_reward * weight.to(last_reward.dtype)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        trajs = tensordict.get(self.prefix) if self.prefix else tensordict
        per_member = self.score(trajs, members=True)
        outputs = {self.out_keys[0]: per_member.mean(0)}
        if self.num_members > 1:
            outputs[self.out_keys[1]] = per_member.movedim(0, -1)
            outputs[self.out_keys[2]] = per_member.std(0)
        batch = per_member.shape[1:]
        if tensordict.batch_dims > len(batch):  # a trajectory batch [N, H]: new [N] output
            return TensorDict(outputs, batch_size=batch, device=tensordict.device)
        for key, value in outputs.items():
            tensordict.set(key, value)
        return tensordict


@torch.no_grad()
def score_trajectories(
    model: ScoreModel,
    trajs: TensorDictBase,
    *,
    batch_size: int = 1024,
    members: bool = False,
) -> torch.Tensor:
    """Score an ``[N, H]`` trajectory batch without gradients, in chunks of ``batch_size``.

    The chunks are moved to the model's device; the result is on the device of ``trajs``.

    Returns:
        ``[N]`` scores (ensemble mean), or ``[C, N]`` with ``members=True``.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=10, horizon=8)
        >>> score_trajectories(ScoreModel(3, 2, num_cells=8), trajs, batch_size=4).shape
        torch.Size([10])
    """
    if trajs.batch_dims != 2:
        raise ValueError(f"score_trajectories: expected an [N, H] batch, got {list(trajs.batch_size)}")
    if batch_size < 1:
        raise ValueError(f"score_trajectories: batch_size must be >= 1, got {batch_size}")
    device = model.gamma.device
    was_training = model.training
    model.eval()
    try:
        chunks = [
            model.score(trajs[i : i + batch_size].to(device), members=True)
            for i in range(0, trajs.batch_size[0], batch_size)
        ]
    finally:
        model.train(was_training)
    out = torch.cat(chunks, -1) if chunks else torch.zeros(model.num_members, 0, device=device)
    out = out if members else out.mean(0)
    if not bool(torch.isfinite(out).all()):
        raise FloatingPointError("score_trajectories: the score model produced NaN/inf scores")
    return out.to(trajs.get("mask").device)


def _pessimistic(per_member: torch.Tensor, kappa: float) -> torch.Tensor:
    """``mean - kappa * std`` over the members (dim 0) of ``[C, N]`` scores; ``kappa = 0``: the mean."""
    return per_member.mean(0) - kappa * per_member.std(0) if kappa else per_member.mean(0)


def _check_kappa(model: ScoreModel, kappa: float, where: str) -> float:
    """``kappa`` as a float, or a ``ValueError`` prefixed by ``where``: finite, >= 0, and > 0 only for an ensemble."""
    kappa = float(kappa)
    if not (math.isfinite(kappa) and kappa >= 0):
        raise ValueError(f"{where}: kappa must be a finite number >= 0, got {kappa}")
    if kappa and model.num_members < 2:
        raise ValueError(f"{where}: kappa={kappa} needs an ensemble (num_members > 1; the spread over members is "
                         f"what it subtracts), got num_members={model.num_members}")
    return kappa


def pessimistic_scores(model: ScoreModel, trajs: TensorDictBase, *, kappa: float = 0.0,
                       batch_size: int = 1024) -> torch.Tensor:
    """``[N]`` ensemble scores of an ``[N, H]`` batch, pessimistic by ``kappa``: the members' mean minus ``kappa``
    times their standard deviation (a lower confidence bound; ``kappa = 0``: :func:`score_trajectories`). No
    gradients; the span :func:`score_objective` normalises by.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=6, horizon=8)
        >>> model = ScoreModel(3, 2, num_cells=8, num_members=3)
        >>> bool((pessimistic_scores(model, trajs, kappa=1.0) <= score_trajectories(model, trajs)).all())
        True
    """
    kappa = _check_kappa(model, kappa, "pessimistic_scores")
    return _pessimistic(score_trajectories(model, trajs, batch_size=batch_size, members=True), kappa)


def score_objective(model: ScoreModel, s_min: float, s_max: float, *,
                    kappa: float = 0.0) -> Callable[[TensorDictBase], torch.Tensor]:
    """A differentiable objective for guided sampling: an ``[N, H]`` batch's :func:`normalized_scores`
    (``s_min -> 0``, ``s_max -> 1``, e.g. the dataset's; the flow's acceptance scale), differentiable in the
    batch's observations and actions (:meth:`TrajectoryDiffuser.generate`'s ``guide``).

    With ``kappa > 0`` (an ensemble only) the objective is pessimistic: the members' mean minus ``kappa`` times
    their spread (:func:`pessimistic_scores`, whose values on the dataset give ``s_min`` / ``s_max``). A guide
    climbing one score model finds directions that model rewards and the task need not (BENCHMARKS #5,
    session 53); members trained apart disagree there, and the bound does not reward the disagreement.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = make_toy_dataset(num_trajectories=4, horizon=8)
        >>> objective = score_objective(ScoreModel(3, 2, num_cells=8), -1.0, 1.0)
        >>> objective(trajs).shape
        torch.Size([4])
    """
    s_min, s_max = float(s_min), float(s_max)
    normalized_scores(torch.tensor([s_min]), s_min, s_max)  # its span check, now rather than at the first step
    kappa = _check_kappa(model, kappa, "score_objective")

    def objective(trajs: TensorDictBase) -> torch.Tensor:
        home = trajs.get("mask").device
        per_member = model.score(trajs.to(model.gamma.device), members=True)
        return normalized_scores(_pessimistic(per_member, kappa), s_min, s_max).to(home)

    return objective


#: ``kind`` tag of score-model checkpoints (:func:`save_score_model`)
SCORE_MODEL_CHECKPOINT = "torchrl_ftb.score_model"


def save_score_model(model: ScoreModel, path: str | os.PathLike, *, extra: dict | None = None) -> Path:
    """Atomically save a score model's constructor numbers and weights (normaliser included).

    Args:
        model: the :class:`ScoreModel`.
        path: target file.
        extra: more ``weights_only``-loadable entries stored beside them.

    Example:
        >>> import tempfile, os
        >>> model = ScoreModel(3, 2, num_cells=8, gamma=0.99, seed=0)
        >>> path = os.path.join(tempfile.mkdtemp(), "score_model.pt")
        >>> loaded = load_score_model(save_score_model(model, path))
        >>> loaded.hparams == model.hparams
        True
    """
    payload = {"kind": SCORE_MODEL_CHECKPOINT, "hparams": dict(model.hparams), "state_dict": model.state_dict(),
               **(extra or {})}
    atomic_torch_save(payload, path)
    return Path(path)


def load_score_model(
    path: str | os.PathLike,
    *,
    model: ScoreModel | None = None,
    map_location: Any = "cpu",
) -> ScoreModel:
    """Load a score model written by :func:`save_score_model` (``torch.load(weights_only=True)``).

    Args:
        path: checkpoint file.
        model: load into this model (its numbers must match the file's); ``None`` rebuilds it
            from the stored ``hparams``.
        map_location: device the checkpoint's tensors are read onto; with ``model`` they are copied into its
            parameters (on its device), without it the rebuilt model is on the CPU (move it with ``.to``).

    Raises:
        FileNotFoundError: no file.
        ValueError: corrupt file, not a score-model checkpoint, or weights that do not fit.
    """
    ckpt = read_checkpoint(path, what="score-model", map_location=map_location)
    if not isinstance(ckpt, dict) or ckpt.get("kind") != SCORE_MODEL_CHECKPOINT or "state_dict" not in ckpt:
        raise ValueError(f"{path}: not a {SCORE_MODEL_CHECKPOINT} checkpoint")
    hparams = ckpt.get("hparams") or {}
    if model is None:
        required = ("observation_dim", "action_dim", "num_cells", "num_layers")
        missing = [k for k in required if k not in hparams]
        if missing:
            raise ValueError(f"{path}: score-model checkpoint lacks hparams {missing}; pass model= to load into")
        model = ScoreModel(hparams["observation_dim"], hparams["action_dim"], num_cells=hparams["num_cells"],
                           num_layers=hparams["num_layers"], num_members=hparams.get("num_members", 1),
                           gamma=hparams.get("gamma", 1.0),
                           reward_activation=hparams.get("reward_activation", "identity"),
                           horizon=hparams.get("horizon"))
    differ = {k: (hparams[k], v) for k, v in model.hparams.items() if k in hparams and hparams[k] != v}
    if differ:
        raise ValueError(f"{path}: score-model checkpoint does not fit the model: (file, model) differ in {differ}")
    try:
        model.load_state_dict(ckpt["state_dict"])
    except (RuntimeError, KeyError) as err:
        raise ValueError(f"{path}: score-model checkpoint (hparams {hparams}) does not fit the model "
                         f"(hparams {model.hparams}): {err}") from err
    return model


def normalized_scores(
    scores: torch.Tensor, s_min: float | torch.Tensor, s_max: float | torch.Tensor
) -> torch.Tensor:
    """``(s - s_min) / (s_max - s_min)``: the flow filter's score scale (dataset in [0, 1]).

    ``s_min``/``s_max`` are floats or tensors broadcasting against ``scores`` (e.g. ``[C, 1]``
    per ensemble member for ``[C, N]`` scores).

    Example:
        >>> normalized_scores(torch.tensor([-3.0, -2.0, -1.0]), -3.0, -1.0).tolist()
        [0.0, 0.5, 1.0]
    """
    s_min = torch.as_tensor(s_min, dtype=scores.dtype)
    span = torch.as_tensor(s_max, dtype=scores.dtype) - s_min
    if not bool((torch.isfinite(span) & (span > 0)).all()):
        raise ValueError(f"normalized_scores: need s_max > s_min (finite), got s_min={s_min.tolist()}, "
                         f"s_max={torch.as_tensor(s_max).tolist()}")
    return (scores - s_min) / span


def with_normalized_scores(
    trajs: TensorDictBase, scores: torch.Tensor, *, s_min: float | None = None, s_max: float | None = None
) -> TensorDictBase:
    """A shallow copy of ``trajs [N, H]`` carrying :data:`NORMALIZED_SCORE_KEY`: each
    trajectory's :func:`normalized_scores` (``scores [N]`` mapped by ``s_min -> 0``,
    ``s_max -> 1``; by default these scores' own minimum and maximum, i.e. ``trajs`` is the
    dataset), repeated over its steps.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> trajs = with_normalized_scores(make_toy_dataset(num_trajectories=3, horizon=4, seed=0),
        ...                                torch.tensor([2.0, 4.0, 3.0]))
        >>> trajs[NORMALIZED_SCORE_KEY][:, 0].tolist()
        [0.0, 1.0, 0.5]
    """
    scores = torch.as_tensor(scores).reshape(-1)
    if scores.shape != trajs.batch_size[:1] or not bool(torch.isfinite(scores).all()):
        raise ValueError(f"with_normalized_scores: scores must be finite [{trajs.batch_size[0]}], "
                         f"got {list(scores.shape)}")
    s_min = float(scores.min()) if s_min is None else s_min
    s_max = float(scores.max()) if s_max is None else s_max
    hat = normalized_scores(scores.double(), s_min, s_max).float()
    out = trajs.clone(False)
    out.set(NORMALIZED_SCORE_KEY, hat.to(trajs.device)[:, None].expand(trajs.batch_size[:2]).clone())
    return out
