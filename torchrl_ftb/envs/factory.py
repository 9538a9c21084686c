"""One entry point from an env *name* to its torchrl env, true reward and score.

Names: ``"toy"`` (:class:`torchrl_ftb.testing.ToyLineEnv`), a Meta-World v3 task
(``"button-press-v3"``, see :func:`metaworld_tasks`) or a locomotion env (``"hopper"``,
``"walker2d"``, ``"halfcheetah"`` or their gymnasium ids ``"Hopper-v5"``, ...). The recipes
(``recipes/ftb_offline.py``, ``recipes/baselines.py``) use these functions; they are public so
that TorchRL code composing our modules gets the same wiring. The matching datasets come from
:func:`torchrl_ftb.datasets.make_dataset`.

Example:
    >>> from functools import partial
    >>> from torchrl_ftb.envs import env_kind, make_env, true_reward_fn
    >>> env_kind("toy"), env_kind("hopper"), env_kind("button-press-v3")
    ('toy', 'locomotion', 'metaworld')
    >>> env = make_env("toy", seed=0, toy_horizon=8)
    >>> td = env.rollout(4)
    >>> reward = true_reward_fn("toy")(td["observation"], td["action"])
    >>> bool((reward == td["next", "reward"]).all())
    True
    >>> make_eval_env = partial(make_env, "toy", seed=1000)  # zero-argument factory for evaluate_policy
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Literal

import torch
from tensordict import TensorDictBase

from torchrl_ftb.data import validate_trajectories
from torchrl_ftb.envs.locomotion import (
    LOCOMOTION_ENVS,
    d4rl_normalized_score,
    locomotion_true_reward,
    make_locomotion_env,
    oracle_step,
)
from torchrl_ftb.envs.metaworld import (
    METAWORLD_OBSERVATION_LAYOUT,
    make_metaworld_env,
    metaworld_tasks,
    metaworld_true_reward,
)

__all__ = [
    "EnvKind", "check_env_matches", "dynamics_oracle", "env_kind", "make_env", "normalized_score_fn",
    "observation_layout", "true_reward_fn",
]

EnvKind = Literal["toy", "metaworld", "locomotion"]


def env_kind(name: str) -> EnvKind:
    """The family of an env name: ``"toy"``, ``"metaworld"`` or ``"locomotion"``.

    Args:
        name: ``"toy"``, a Meta-World v3 task (``"button-press-v3"``) or a locomotion env
            (``"hopper"``/``"walker2d"``/``"halfcheetah"`` or ``"Hopper-v5"``, ...).

    Raises:
        ValueError: any other name (the message lists the valid ones).

    Example:
        >>> env_kind("walker2d"), env_kind("Walker2d-v5")
        ('locomotion', 'locomotion')
    """
    if name == "toy":
        return "toy"
    if name in LOCOMOTION_ENVS or name in LOCOMOTION_ENVS.values():
        return "locomotion"
    tasks = metaworld_tasks()
    if name in tasks:
        return "metaworld"
    raise ValueError(
        f"unknown env {name!r}: expected 'toy', a locomotion env ({', '.join(LOCOMOTION_ENVS)} or "
        f"{', '.join(LOCOMOTION_ENVS.values())}) or a Meta-World v3 task ({', '.join(tasks)})"
    )


def make_env(
    name: str,
    *,
    seed: int,
    max_episode_steps: int | None = None,
    toy_horizon: int = 32,
    random_goal: bool = True,
    device: str | torch.device = "cpu",
):
    """A seeded torchrl env for ``name`` (see :func:`env_kind`).

    Args:
        name: env name.
        seed: env seed.
        max_episode_steps: time limit (truncation). Meta-World: default 500
            (:func:`make_metaworld_env`); locomotion: default the gymnasium limit (1000), a
            value adds a :class:`torchrl.envs.StepCounter` limit; toy: ignored (``toy_horizon``).
        toy_horizon: the toy env's episode length.
        random_goal: Meta-World only: draw a new (seeded) goal / object placement at every
            reset, as MT1 evaluation does. With ``False`` every episode starts from the same
            goal and state, so N evaluation episodes of a deterministic policy are one episode
            repeated N times.
        device: torch device of the env outputs.

    Returns:
        A torchrl ``EnvBase`` with ``"observation"`` and ``"action"`` (float32); Meta-World and
        toy envs also write ``("next", "success")``. For :func:`evaluate_policy
        <torchrl_ftb.policy.evaluate_policy>`, wrap it as a zero-argument factory, e.g.
        ``functools.partial(make_env, name, seed=1000)``.

    Raises:
        ValueError: unknown name.

    Example:
        >>> env = make_env("button-press-v3", seed=0, max_episode_steps=5)
        >>> env.action_spec.shape, env.rollout(5)["observation"].shape
        (torch.Size([4]), torch.Size([5, 39]))
    """
    kind = env_kind(name)
    if kind == "toy":
        from torchrl_ftb.testing import ToyLineEnv

        env = ToyLineEnv(max_steps=int(toy_horizon), device=device)
        env.set_seed(int(seed))
        return env
    if kind == "metaworld":
        kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
        return make_metaworld_env(name, seed=int(seed), device=device, random_goal=random_goal, **kwargs)
    env = make_locomotion_env(name, seed=int(seed), device=device)
    if max_episode_steps is not None:
        from torchrl.envs import StepCounter

        env.append_transform(StepCounter(max_steps=int(max_episode_steps)))
    return env


def observation_layout(name: str) -> dict:
    """Known structure of an env's observation, as :func:`~torchrl_ftb.diffusion.make_diffuser`
    keyword arguments (``lagged_dims``, ``time_constant_dims``); ``{}`` when there is none
    (toy, locomotion).

    Example:
        >>> observation_layout("toy")
        {}
        >>> observation_layout("button-press-v3")["time_constant_dims"]
        (36, 37, 38)
    """
    return dict(METAWORLD_OBSERVATION_LAYOUT) if env_kind(name) == "metaworld" else {}


def _metaworld_reward(task: str, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    return metaworld_true_reward(task, observation, action)[0]


def true_reward_fn(name: str, *, with_success: bool = False) -> Callable[[torch.Tensor, torch.Tensor], Any]:
    """Ground-truth reward ``fn(observation, action) -> reward [..., 1]`` of ``name``'s env.

    Toy: :func:`torchrl_ftb.testing.toy_reward` (closed form). Meta-World:
    :func:`metaworld_true_reward` on an observation *sequence* ``[H, 39]`` (or ``[N, H, 39]``;
    its next observations are the sequence shifted by one step). Locomotion:
    :func:`locomotion_true_reward` (exact, per transition). Meant for statistics, e.g.
    ``FlowToBetter(..., true_reward_fn=true_reward_fn(name))``.

    ``with_success=True`` (Meta-World only): ``fn`` returns ``(reward, success)`` from the same
    simulator pass, for the stop-rule cut of ``FlowToBetter(true_return_streak=...)``.

    Raises:
        ValueError: unknown name; ``with_success`` for an env without a success signal.

    Example:
        >>> import torch
        >>> true_reward_fn("toy")(torch.zeros(5, 3), torch.ones(5, 2)).shape
        torch.Size([5, 1])
    """
    kind = env_kind(name)
    if with_success:
        if kind != "metaworld":
            raise ValueError(f"true_reward_fn({name!r}, with_success=True): only Meta-World envs have a per-step "
                             "success signal")
        return functools.partial(metaworld_true_reward, name)
    if kind == "toy":
        from torchrl_ftb.testing import toy_reward

        return toy_reward
    if kind == "metaworld":
        return functools.partial(_metaworld_reward, name)
    return functools.partial(locomotion_true_reward, name)


def dynamics_oracle(name: str, *, toy_horizon: int | None = None
                    ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None:
    """Ground-truth one-step dynamics ``fn(observation, action) -> next observation`` of ``name``'s env,
    or ``None`` where there is none to call.

    Toy: :func:`torchrl_ftb.analysis.toy_oracle_step` (closed form; its time feature needs
    ``toy_horizon``). Locomotion: :func:`torchrl_ftb.envs.oracle_step` (the simulator rebuilt from
    each observation). Meta-World: ``None``: its observation holds neither joint velocities nor the
    object's full state, so no simulator state can be rebuilt from it (its physics proxies,
    :func:`metaworld_physics_errors`, stand in). Meant for the validity analysis
    (:func:`torchrl_ftb.analysis.dynamics_error`).

    Raises:
        ValueError: unknown name; toy without ``toy_horizon``.

    Example:
        >>> import torch
        >>> step = dynamics_oracle("toy", toy_horizon=8)
        >>> step(torch.zeros(2, 3), torch.ones(2, 2)).shape
        torch.Size([2, 3])
        >>> dynamics_oracle("button-press-v3") is None
        True
    """
    kind = env_kind(name)
    if kind == "metaworld":
        return None
    if kind == "locomotion":
        return functools.partial(oracle_step, name)
    if toy_horizon is None:
        raise ValueError("dynamics_oracle('toy'): pass toy_horizon (the toy dataset's horizon)")
    from torchrl_ftb.analysis.metrics import toy_oracle_step  # here: the analysis package pulls in matplotlib

    return functools.partial(toy_oracle_step, horizon=int(toy_horizon))


def _d4rl_score(name: str, mean_return: float) -> float:
    return float(d4rl_normalized_score(name, mean_return))


def normalized_score_fn(name: str) -> Callable[[float], float] | None:
    """Return → normalised score for ``name``'s env, or ``None`` where the paper reports none.

    Locomotion: the D4RL normalized score ``100 * (R - R_random) / (R_expert - R_random)``
    (:func:`d4rl_normalized_score`); toy and Meta-World (success rate instead): ``None``.
    Pass it to ``evaluate_policy(..., normalized_score_fn=...)``.

    Raises:
        ValueError: unknown name.

    Example:
        >>> normalized_score_fn("hopper")(3234.3), normalized_score_fn("toy")
        (100.0, None)
    """
    if env_kind(name) != "locomotion":
        return None
    return functools.partial(_d4rl_score, name)


def check_env_matches(
    make_env_fn: Callable[[], object], trajectories: TensorDictBase, *, name: str
) -> tuple[int, int]:
    """Check a trajectory batch against an env's observation/action dims.

    Args:
        make_env_fn: zero-argument env factory (the env is built, read and closed).
        trajectories: ``[N, H]`` trajectory batch (``docs/conventions.md``).
        name: env name for the error message.

    Returns:
        ``(obs_dim, action_dim)`` of the env.

    Raises:
        ValueError: the dataset is malformed or its dims differ from the env's.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> check_env_matches(functools.partial(make_env, "toy", seed=0),
        ...                   make_toy_dataset(num_trajectories=2, horizon=4), name="toy")
        (3, 2)
    """
    env = make_env_fn()
    try:
        obs_dim = int(env.observation_spec["observation"].shape[-1])
        act_dim = int(env.action_spec.shape[-1])
    finally:
        env.close()
    validate_trajectories(trajectories, name=f"dataset for env {name!r}", obs_dim=obs_dim, action_dim=act_dim)
    return obs_dim, act_dim
