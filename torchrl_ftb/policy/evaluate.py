"""Evaluation rollouts of a policy through torchrl environments.

Episodes are run with ``env.rollout``; with ``num_envs > 1`` a :class:`~torchrl.envs.SerialEnv`
runs them in lock-step (finished envs are no longer stepped, ``break_when_all_done``).
Each episode counts up to and including its first ``done``. Meta-World style evaluation
(episodes end at the first success, as the authors did) is the ``stop_on_success`` option,
implemented with torchrl's :class:`~torchrl.envs.transforms.TerminateTransform`.

Example:
    >>> from torchrl_ftb.policy import evaluate_policy, make_bc_actor
    >>> from torchrl_ftb.testing import ToyLineEnv
    >>> actor = make_bc_actor(3, 2, hidden=(8,))
    >>> out = evaluate_policy(lambda: ToyLineEnv(max_steps=8), actor, num_episodes=2, seed=0, max_steps=8)
    >>> sorted(out)
    ['length_mean', 'num_episodes', 'return_mean', 'return_std', 'success_rate']
"""
from __future__ import annotations

import inspect
import math
from typing import Any, Callable, Mapping

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.envs import EnvBase, SerialEnv, TransformedEnv
from torchrl.envs.transforms import TerminateTransform
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from torchrl_ftb.policy.bc import check_bc_options, check_number

__all__ = ["evaluate_policy", "episode_statistics"]


def episode_statistics(rollout: TensorDictBase) -> dict[str, torch.Tensor]:
    """Per-episode return, length and success of a rollout ``[n, T]`` (or ``[T]``).

    Steps after an env's first ``("next", "done")`` are ignored (they are copies or belong
    to the next episode).

    Returns:
        ``{"return": [n], "length": [n], "success": [n] bool}`` (``success`` only if the
        rollout has ``("next", "success")``).
    """
    if rollout.batch_dims == 1:
        rollout = rollout.unsqueeze(0)
    done = rollout.get(("next", "done")).reshape(*rollout.batch_size).bool()
    steps = torch.arange(done.shape[1], device=done.device)
    big = torch.full_like(steps, done.shape[1] - 1)
    first_done = torch.where(done, steps.expand_as(done), big.expand_as(done)).min(1).values
    valid = steps[None, :] <= first_done[:, None]
    reward = rollout.get(("next", "reward")).reshape(*rollout.batch_size).float()
    out = {"return": (reward * valid).sum(1), "length": valid.sum(1)}
    if ("next", "success") in rollout.keys(True):
        success = rollout.get(("next", "success")).reshape(*rollout.batch_size).bool()
        out["success"] = (success & valid).any(1)
    return out


#: ``evaluate_policy(max_steps=None)``'s cap: the env's own time limit ends every episode long before
UNTIL_DONE_STEPS = 1_000_000


def check_evaluation_options(*, num_episodes: int = 10, num_envs: int = 1, max_steps: int | None = 1000) -> None:
    """Check :func:`evaluate_policy`'s numbers (same names and defaults) without building an env.

    A recipe calls it before any training, so a bad evaluation option fails in seconds instead of after
    training; :func:`evaluate_policy` calls it too.

    Raises:
        ValueError: naming the first option out of range.

    Example:
        >>> check_evaluation_options(num_episodes=50, num_envs=5, max_steps=500)
        >>> check_evaluation_options(num_episodes=0)
        Traceback (most recent call last):
        ...
        ValueError: evaluate_policy: num_episodes must be >= 1, got 0
    """
    for name, value in (("num_episodes", num_episodes), ("num_envs", num_envs), ("max_steps", max_steps)):
        if value is None and name == "max_steps":  # the env's own time limit
            continue
        check_number("evaluate_policy", name, value, whole=True)
        if value < 1:
            raise ValueError(f"evaluate_policy: {name} must be >= 1, got {value}")


def check_policy_sections(sections: Mapping[str, Mapping[str, Any] | None]) -> None:
    """A recipe's ``bc`` and ``eval`` config sections checked at start by :func:`check_bc_options` and
    :func:`check_evaluation_options`, each error prefixed with its section (``"bc.*: train_bc: lr must be > 0"``).

    Args:
        sections: ``{"bc": ..., "eval": ...}`` (either may be left out): each a mapping holding at least the
            check's options (other keys, e.g. ``hidden`` or ``seed``, are ignored).

    Example:
        >>> check_policy_sections({"bc": {"steps": 100, "batch_size": 64, "lr": 1e-4, "weight_decay": 0.0},
        ...                        "eval": {"num_episodes": 10, "num_envs": 1, "max_steps": None, "seed": 0}})
        >>> check_policy_sections({"eval": {"num_episodes": 2.5, "num_envs": 1, "max_steps": 500}})
        Traceback (most recent call last):
        ...
        ValueError: eval.*: evaluate_policy: num_episodes must be a whole number, got 2.5
    """
    checks = {"bc": check_bc_options, "eval": check_evaluation_options}
    for section, values in sections.items():
        check = checks[section]
        try:  # the options are the check's own keyword arguments
            check(**{key: values.get(key) for key in inspect.signature(check).parameters})
        except ValueError as err:
            raise ValueError(f"{section}.*: {err}") from None


def evaluate_policy(
    make_env: Callable[[], EnvBase],
    actor: TensorDictModule,
    *,
    num_episodes: int = 10,
    seed: int = 0,
    max_steps: int | None = 1000,
    num_envs: int = 1,
    stop_on_success: bool = False,
    normalized_score_fn: Callable[[float], float] | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Roll out ``actor`` deterministically for ``num_episodes`` episodes and summarise.

    Args:
        make_env: zero-argument factory of a torchrl env (e.g. ``lambda: make_metaworld_env(task)``).
        actor: policy writing ``"action"``; run under ``no_grad`` and deterministic exploration.
        num_episodes: number of episodes.
        seed: env seed (episodes are reproducible for a given seed).
        max_steps: per-episode step limit; ``None``: the env's own time limit (every episode runs until
            the env ends it; capped at :data:`UNTIL_DONE_STEPS`), e.g. 500 on Meta-World, 1000 on locomotion.
        num_envs: episodes run side by side in a ``SerialEnv``.
        stop_on_success: end an episode at its first ``success`` (Meta-World protocol).
        normalized_score_fn: maps a mean return to a normalised score (e.g. D4RL's
            ``100 * (R - min) / (max - min)``); adds ``"normalized_score"`` (mean over episodes)
            and its std.
        progress: show a tqdm bar over rounds.

    Returns:
        ``{"num_episodes", "return_mean", "return_std", "length_mean"}`` plus
        ``"success_rate"`` if the env reports ``success`` and ``"normalized_score"``,
        ``"normalized_score_std"`` if ``normalized_score_fn`` is given.

    Raises:
        ValueError: numbers out of range (:func:`check_evaluation_options`), or ``stop_on_success`` on an env
            without a ``success`` entry.
    """
    check_evaluation_options(num_episodes=num_episodes, num_envs=num_envs, max_steps=max_steps)
    # whole numbers (checked); a config's 500.0 is 500
    num_episodes, num_envs = int(num_episodes), int(num_envs)
    max_steps = None if max_steps is None else int(max_steps)
    num_envs = min(num_envs, num_episodes)
    env = make_env() if num_envs == 1 else SerialEnv(num_envs, make_env)
    if stop_on_success:
        if ("next", "success") not in env.full_observation_spec.keys(True) and "success" not in env.full_observation_spec.keys(True):
            raise ValueError("evaluate_policy: stop_on_success=True but the env has no 'success' entry")
        stop = TerminateTransform(lambda td: td.get("success"))
        if isinstance(env, TransformedEnv):  # our own fresh env: extend its transforms, don't nest
            env.append_transform(stop)
        else:
            env = TransformedEnv(env, stop)
    env.set_seed(int(seed))
    was_training = actor.training
    actor.eval()
    stats: dict[str, list[torch.Tensor]] = {}
    rounds = math.ceil(num_episodes / num_envs)
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in tqdm(range(rounds), desc="eval", disable=not progress):
                rollout = env.rollout(
                    UNTIL_DONE_STEPS if max_steps is None else max_steps,
                    actor,
                    auto_cast_to_device=True,
                    break_when_any_done=num_envs == 1,
                    break_when_all_done=num_envs > 1 or None,
                )
                for k, v in episode_statistics(rollout).items():
                    stats.setdefault(k, []).append(v.cpu())
    finally:
        env.close()
        actor.train(was_training)
    per_ep = {k: torch.cat(v)[:num_episodes] for k, v in stats.items()}
    returns = per_ep["return"].double()
    out: dict[str, Any] = {
        "num_episodes": int(returns.numel()),
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std(unbiased=False)),
        "length_mean": float(per_ep["length"].double().mean()),
    }
    if "success" in per_ep:
        out["success_rate"] = float(per_ep["success"].double().mean())
    if normalized_score_fn is not None:
        scores = torch.tensor([float(normalized_score_fn(float(r))) for r in returns], dtype=torch.float64)
        out["normalized_score"] = float(scores.mean())
        out["normalized_score_std"] = float(scores.std(unbiased=False))
    return out
