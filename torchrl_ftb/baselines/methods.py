"""The Table-1 baselines as one function: ``run_baseline(method, trajs, labels=...)``.

Every method trains on the same ``[N, H]`` trajectory batch (and, for the preference-based
ones, the same labels) that FTB uses, and returns a deterministic actor reading
``"observation"`` for :func:`torchrl_ftb.policy.evaluate_policy`:

============== ==================================================================================
method         what it is
============== ==================================================================================
``bc``         BC (torchrl_ftb.policy) on every transition
``bc10``       10%BC: BC on the top ``top_fraction`` trajectories by **true** return
``bc10_score`` 10%BC ranked by the learned score s_ψ (labels only; labelled as such in tables)
``td3bc``      TD3+BC (α = 2.5) on the true reward
``iql``        IQL (τ = 0.7, β = 3.0) on the true reward
``iql_rpsi``   IQL + r_ψ: IQL on the transition reward learned from the labels (one MLP)
``oprl``       OPRL: IQL on the mean of an ensemble of learned rewards (Shin et al., 2022);
               its active query selection is the labels' choice, shared by every method
               (``labels.query.strategy=disagreement`` in the recipes,
               :func:`torchrl_ftb.preference.make_query_labels`)
``iql_zero``   IQL with zero reward (sanity check: what the BC-like part of IQL alone gives)
============== ==================================================================================

Learned rewards are attached to the replay buffer as a sample-time ``ModuleTransform``
(:func:`~torchrl_ftb.baselines.make_reward_transforms`), then rescaled with the same
normalisation as the true reward.

Example:
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> from torchrl_ftb.baselines import run_baseline
    >>> trajs = make_toy_dataset(num_trajectories=16, horizon=8, seed=0)
    >>> result = run_baseline("iql_zero", trajs, seed=0, progress=False,
    ...                       network={"hidden": [16]}, iql={"steps": 3, "batch_size": 16})
    >>> result.method, sorted(result.actor.in_keys)
    ('iql_zero', ['observation'])
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_ftb.baselines.data import (
    REWARD_KEY,
    make_offline_buffer,
    make_reward_transforms,
    select_top_trajectories,
    zero_reward_module,
)
from torchrl_ftb.baselines.networks import make_iql_model, make_td3bc_model
from torchrl_ftb.baselines.offline_rl import train_iql, train_td3bc
from torchrl_ftb.data import trajectories_to_flat, validate_trajectories
from torchrl_ftb.data.labels import ReturnTeacher
from torchrl_ftb.policy import make_bc_actor_for, observation_statistics, train_bc

__all__ = ["METHODS", "LABEL_METHODS", "TRUE_REWARD_METHODS", "BaselineResult", "run_baseline",
           "train_reward_model"]

METHODS: dict[str, str] = {
    "bc": "BC (all data)",
    "bc10": "10%BC (top 10% by true return)",
    "bc10_score": "10%BC (top 10% by learned score s_psi)",
    "td3bc": "TD3+BC (true reward)",
    "iql": "IQL (true reward)",
    "iql_rpsi": "IQL + r_psi (learned reward)",
    "oprl": "OPRL (IQL + ensemble-mean learned reward)",
    "iql_zero": "IQL (zero reward, sanity check)",
}
#: methods that learn from the preference labels
LABEL_METHODS = frozenset({"bc10_score", "iql_rpsi", "oprl"})
#: methods that read the true reward of the dataset
TRUE_REWARD_METHODS = frozenset({"bc10", "td3bc", "iql"})


@dataclass
class BaselineResult:
    """What :func:`run_baseline` returns.

    Attributes:
        method: the method name.
        actor: deterministic policy ``"observation"`` → ``"action"`` (eval mode).
        info: training statistics (losses, wall time, selected trajectories, reward model).
        reward_model: the learned score/reward model, for the label-based methods.
    """

    method: str
    actor: TensorDictModuleBase
    info: dict[str, Any] = field(default_factory=dict)
    reward_model: torch.nn.Module | None = None


def train_reward_model(
    trajs: TensorDictBase,
    labels: TensorDictBase,
    *,
    num_members: int = 1,
    model: Mapping[str, Any] | None = None,
    training: Mapping[str, Any] | None = None,
    seed: int = 0,
    logger=None,
    progress: bool = True,
    device: torch.device | str | None = None,
):
    """Train the preference stage's :class:`~torchrl_ftb.preference.ScoreModel` on ``labels``.

    Args:
        trajs: the dataset (its dimensions, and its observations for the normaliser).
        labels: preference labels (docs/conventions.md).
        num_members: ensemble size (1: IQL + r_ψ / 10%BC by score; > 1: OPRL).
        model: extra ``ScoreModel`` keyword arguments (``num_cells``, ``num_layers``, ``gamma``,
            ``reward_activation``, ``horizon``)
            and ``normalize_observations`` (fit the model's observation normaliser on ``trajs``
            before training; default off).
        training: ``train_score_model`` keyword arguments (``steps``, ``lr``, ``batch_size`` ...).
        seed: initialisation and training seed.

    Returns:
        ``(score_model, train_stats)``; the model is in eval mode, its ``reward_module``
        writes the (ensemble-mean) per-step reward ``("next", "reward")``.
    """
    from torchrl_ftb.preference import ScoreModel, train_score_model

    obs_dim, act_dim = trajs.get("observation").shape[-1], trajs.get("action").shape[-1]
    model = dict(model or {})
    normalize = bool(model.pop("normalize_observations", False))
    score_model = ScoreModel(obs_dim, act_dim, **model, num_members=int(num_members), seed=seed, device=device)
    if normalize:
        score_model.fit_normalizer(trajs)
    stats = train_score_model(score_model, labels, **dict(training or {}), seed=seed, logger=logger,
                              progress=progress, device=device)
    score_model.eval()
    return score_model, stats


def run_baseline(
    method: str,
    trajs: TensorDictBase,
    *,
    labels: TensorDictBase | None = None,
    seed: int = 0,
    network: Mapping[str, Any] | None = None,
    bc: Mapping[str, Any] | None = None,
    iql: Mapping[str, Any] | None = None,
    td3bc: Mapping[str, Any] | None = None,
    top_fraction: float = 0.1,
    teacher: ReturnTeacher | None = None,
    reward_normalization: str = "return_range",
    reward_model: Mapping[str, Any] | None = None,
    reward_training: Mapping[str, Any] | None = None,
    oprl_members: int = 5,
    logger=None,
    progress: bool = True,
    device: torch.device | str | None = None,
) -> BaselineResult:
    """Train one baseline on a trajectory batch and return its policy.

    Args:
        method: one of :data:`METHODS`.
        trajs: ``[N, H]`` dataset (docs/conventions.md), the same FTB uses.
        labels: preference labels — required by :data:`LABEL_METHODS`.
        seed: seeds networks, sampling and the reward model.
        network: ``{"hidden": [256, 256]}`` — hidden widths of the actor/critics (BC included).
        bc: :func:`~torchrl_ftb.policy.train_bc` keyword arguments (``steps``, ``batch_size``,
            ``lr``, ``weight_decay``) and optionally ``hidden`` (default: ``network["hidden"]``).
        iql: ``batch_size`` + :func:`~torchrl_ftb.baselines.train_iql` keyword arguments.
        td3bc: ``batch_size`` + :func:`~torchrl_ftb.baselines.train_td3bc` keyword arguments.
        top_fraction: share of trajectories 10%BC keeps.
        teacher: the labels' scripted teacher; 10%BC ranks by its return definition
            (``teacher.returns``: discount, stop-rule horizon). Default: the paper's
            undiscounted return.
        reward_normalization: ``"none" | "return_range" | "standardize"`` for every IQL/TD3+BC
            reward, true or learned (see :func:`~torchrl_ftb.baselines.reward_scale`).
        reward_model: ``ScoreModel`` keyword arguments for the learned rewards.
        reward_training: ``train_score_model`` keyword arguments.
        oprl_members: ensemble size of OPRL's reward.
        logger: torchrl logger, optional.
        progress: tqdm bars.
        device: training device.

    Raises:
        ValueError: unknown method, missing labels, or a method that needs the true reward on
            reward-free data.
    """
    if method not in METHODS:
        raise ValueError(f"unknown baseline method {method!r}; choose from {sorted(METHODS)}")
    validate_trajectories(trajs, name="dataset")
    if method in LABEL_METHODS and (labels is None or labels.batch_size[0] < 1):
        raise ValueError(f"method {method!r} learns from preference labels, but no labels were given")
    if method in TRUE_REWARD_METHODS and REWARD_KEY not in trajs.keys(True):
        raise ValueError(f"method {method!r} needs the true reward ('next', 'reward'), which the dataset lacks")
    section = "bc" if method.startswith("bc") else method if method == "td3bc" else "iql"
    if "steps" not in dict({"bc": bc, "td3bc": td3bc, "iql": iql}[section] or {}):
        raise ValueError(f"method {method!r}: give the number of gradient steps as {section}['steps']")
    hidden = list((network or {}).get("hidden", [256, 256]))
    obs_dim, act_dim = trajs.get("observation").shape[-1], trajs.get("action").shape[-1]
    info: dict[str, Any] = {"method": method, "description": METHODS[method]}
    teacher = ReturnTeacher() if teacher is None else teacher
    score_model = None

    if method in ("bc", "bc10", "bc10_score"):
        selected = trajs
        if method == "bc10":
            selected, idx = select_top_trajectories(trajs, teacher.returns(trajs), fraction=top_fraction)
            info["selected_trajectories"] = int(idx.numel())
            info["ranked_by"] = f"true return ({teacher.name})"
        elif method == "bc10_score":
            from torchrl_ftb.preference import score_trajectories

            score_model, info["reward_model"] = train_reward_model(
                trajs, labels, model=reward_model, training=reward_training, seed=seed, logger=logger,
                progress=progress, device=device)
            scores = score_trajectories(score_model, trajs)
            selected, idx = select_top_trajectories(trajs, scores.cpu(), fraction=top_fraction)
            info["selected_trajectories"] = int(idx.numel())
            info["ranked_by"] = "learned score s_psi"
        if method != "bc" and REWARD_KEY in trajs.keys(True):
            info["selected_true_return_mean"] = float(teacher.returns(selected).mean())
            info["dataset_true_return_mean"] = float(teacher.returns(trajs).mean())
        flat = trajectories_to_flat(selected).select("observation", "action")
        bc_opts = dict(bc or {})
        actor = make_bc_actor_for(flat, hidden=list(bc_opts.pop("hidden", hidden)), device=device)
        info["train"] = train_bc(actor, flat, **bc_opts, seed=seed, logger=logger, progress=progress, device=device)
        actor.eval()
        return BaselineResult(method, actor, info, score_model)

    # actor-critic methods: the reward the agent sees
    reward_module = None
    if method == "iql_zero":
        reward_module = zero_reward_module()
    elif method in ("iql_rpsi", "oprl"):
        score_model, info["reward_model"] = train_reward_model(
            trajs, labels, num_members=oprl_members if method == "oprl" else 1, model=reward_model,
            training=reward_training, seed=seed, logger=logger, progress=progress, device=device)
        reward_module = score_model.reward_module
    transforms = make_reward_transforms(trajs, reward_module=reward_module, normalization=reward_normalization)
    loc, scale = observation_statistics(trajectories_to_flat(trajs).get("observation"))
    opts = dict((td3bc if method == "td3bc" else iql) or {})
    batch_size = int(opts.pop("batch_size", 256))
    # storage on the training device: sampled batches meet the reward module where it lives
    buffer = make_offline_buffer(trajs, batch_size=batch_size, seed=seed, transforms=transforms,
                                 require_reward=reward_module is None, device=device)
    if method == "td3bc":
        model = make_td3bc_model(obs_dim, act_dim, hidden=hidden, obs_loc=loc, obs_scale=scale, device=device)
        info["train"] = train_td3bc(model, buffer, **opts, seed=seed, logger=logger, progress=progress, device=device)
    else:
        model = make_iql_model(obs_dim, act_dim, hidden=hidden, obs_loc=loc, obs_scale=scale, device=device)
        info["train"] = train_iql(model, buffer, **opts, seed=seed, logger=logger, progress=progress, device=device)
    actor = model[0]
    actor.eval()
    return BaselineResult(method, actor, info, score_model)
