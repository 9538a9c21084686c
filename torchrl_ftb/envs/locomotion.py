"""MuJoCo locomotion (Hopper / Walker2d / HalfCheetah v5): envs, D4RL scores and an oracle.

The observation of these envs is ``qpos[1:] ‖ qvel`` (the x position is left out, and it
does not affect the dynamics), so the simulator state can be rebuilt from an observation:
:func:`oracle_step` steps it, :func:`locomotion_true_reward` gives the exact reward of
``(s, a)``, so ``torchrl_ftb.analysis.dynamics_error(trajs, partial(oracle_step, env))`` checks
generated transitions against the simulator.
:func:`replay_locomotion_actions` runs a trajectory's actions open loop from its first observation;
:func:`track_locomotion_paths` follows its observations in closed loop instead.
One caveat: Hopper and Walker2d clip the velocities in the observation to ±10, so a state
whose true velocity exceeded that is rebuilt with the clipped value.

Example:
    >>> import torch
    >>> from torchrl_ftb.envs import make_locomotion_env, oracle_step
    >>> env = make_locomotion_env("hopper", seed=0)
    >>> td = env.rollout(3)
    >>> nxt = oracle_step("hopper", td["observation"], td["action"])
    >>> bool(torch.allclose(nxt, td["next", "observation"], atol=1e-4))
    True
"""
from __future__ import annotations

import functools
import zlib

import numpy as np
import torch

from torchrl_ftb.envs.sim_state import shoot

__all__ = [
    "LOCOMOTION_ENVS",
    "D4RL_REF_SCORES",
    "locomotion_env_id",
    "make_locomotion_env",
    "d4rl_normalized_score",
    "oracle_step",
    "locomotion_true_reward",
    "replay_locomotion_actions",
    "track_locomotion_paths",
]

LOCOMOTION_ENVS = {"hopper": "Hopper-v5", "walker2d": "Walker2d-v5", "halfcheetah": "HalfCheetah-v5"}
# D4RL reference returns (random, expert) used by its normalized score (see datasets.md).
D4RL_REF_SCORES = {
    "hopper": (-20.272305, 3234.3),
    "halfcheetah": (-280.178953, 12135.0),
    "walker2d": (1.629008, 4592.3),
}


def _short_name(name: str) -> str:
    key = name.lower().replace("_", "").replace("-", "")
    for short in LOCOMOTION_ENVS:
        if key.startswith(short):
            return short
    raise ValueError(
        f"unknown locomotion env {name!r}; valid: {', '.join(LOCOMOTION_ENVS)} "
        f"(or {', '.join(LOCOMOTION_ENVS.values())}, or a D4RL id such as 'hopper-medium-v2')"
    )


def locomotion_env_id(name: str) -> str:
    """Gymnasium id of a locomotion env from a short name, a gymnasium id or a D4RL id.

    Example:
        >>> locomotion_env_id("hopper"), locomotion_env_id("walker2d-medium-replay-v2")
        ('Hopper-v5', 'Walker2d-v5')
    """
    return LOCOMOTION_ENVS[_short_name(name)]


def make_locomotion_env(name: str, *, seed: int = 0, device: str | torch.device = "cpu"):
    """A TorchRL locomotion env: ``GymEnv(<name>-v5)`` with float32 observations.

    Args:
        name: ``"hopper"``, ``"walker2d"``, ``"halfcheetah"`` or the gymnasium id.
        seed: env seed.
        device: torch device.

    Example:
        >>> env = make_locomotion_env("halfcheetah")
        >>> env.rollout(2)["observation"].dtype
        torch.float32
    """
    from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv

    env = TransformedEnv(GymEnv(locomotion_env_id(name), device=device), DoubleToFloat())
    env.set_seed(int(seed))
    return env


def d4rl_normalized_score(env_name: str, returns: torch.Tensor | np.ndarray | float) -> torch.Tensor:
    """D4RL normalized score ``100 * (R - R_random) / (R_expert - R_random)``.

    Example:
        >>> float(d4rl_normalized_score("hopper", 3234.3))
        100.0
    """
    lo, hi = D4RL_REF_SCORES[_short_name(env_name)]
    r = torch.as_tensor(returns, dtype=torch.float64)
    return (100.0 * (r - lo) / (hi - lo)).to(torch.float32)


@functools.lru_cache(maxsize=4)
def _sim(env_id: str):
    import gymnasium as gym

    env = gym.make(env_id)
    env.reset(seed=0)
    return env.unwrapped


def _state_from_obs(u, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(qpos, qvel)`` of the simulator state an observation shows (x = 0: the observation omits it)."""
    nq = u.model.nq
    return np.concatenate([[0.0], obs[: nq - 1]]), obs[nq - 1 :]


def _set_from_obs(u, obs: np.ndarray) -> None:
    """The simulator at the state of ``obs`` (x = 0) with a fresh ``mjData``, as a reset leaves it: without
    ``mj_resetData`` the contact solver's warm start of whatever ran before would carry over, and on
    HalfCheetah's many contacts change the outcome, so a reading would depend on the order of the calls
    (``bench/locomotion_fidelity.py`` shows that effect)."""
    import mujoco

    mujoco.mj_resetData(u.model, u.data)
    u.set_state(*_state_from_obs(u, obs))


def _flat(x, name: str, dim: int | None = None) -> tuple[np.ndarray, tuple]:
    arr = x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)
    if dim is not None and arr.shape[-1] != dim:
        raise ValueError(f"{name}: last dimension {arr.shape[-1]} != {dim} expected by the env")
    return arr.reshape(-1, arr.shape[-1]), arr.shape[:-1]


def _check_dims(u, obs: np.ndarray, act: np.ndarray, env_id: str) -> None:
    obs_dim = u.model.nq - 1 + u.model.nv
    if obs.shape[-1] != obs_dim:
        raise ValueError(f"observation: last dimension {obs.shape[-1]} != {obs_dim} of {env_id}")
    if act.shape[-1] != u.model.nu:
        raise ValueError(f"action: last dimension {act.shape[-1]} != {u.model.nu} of {env_id}")
    if obs.shape[0] != act.shape[0]:
        raise ValueError(f"observation and action batch shapes differ ({obs.shape[0]} vs {act.shape[0]})")


def oracle_step(env_name: str, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """True next observation of ``(s, a)``: rebuild the MuJoCo state from ``s`` and step.

    Args:
        env_name: locomotion env (see :func:`locomotion_env_id`).
        observation: ``[..., obs_dim]``.
        action: ``[..., act_dim]`` (same leading shape).

    Returns:
        ``[..., obs_dim]`` float32 next observations.
    """
    env_id = locomotion_env_id(env_name)
    u = _sim(env_id)
    obs, lead = _flat(observation, "observation")
    act, _ = _flat(action, "action")
    _check_dims(u, obs, act, env_id)
    out = np.empty_like(obs)
    for i in range(len(obs)):
        _set_from_obs(u, obs[i])
        u.do_simulation(np.clip(act[i], -1.0, 1.0), u.frame_skip)
        out[i] = u._get_obs()
    return torch.from_numpy(out).float().reshape(*lead, obs.shape[-1])


def locomotion_true_reward(env_name: str, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Exact env reward ``r(s, a)`` of locomotion transitions (shape ``[..., 1]``, float32).

    The simulator is reset to each observation (x = 0, which does not change the reward)
    and stepped with the env's own ``step``; the next state is then a function of
    ``(s, a)``, so no next observation is needed (compare generated next observations with
    ``torchrl_ftb.analysis.dynamics_error``).

    Example:
        >>> env = make_locomotion_env("hopper")
        >>> td = env.rollout(4)
        >>> r = locomotion_true_reward("hopper", td["observation"], td["action"])
        >>> bool(torch.allclose(r, td["next", "reward"], atol=1e-4))
        True
    """
    env_id = locomotion_env_id(env_name)
    u = _sim(env_id)
    obs, lead = _flat(observation, "observation")
    act, _ = _flat(action, "action")
    _check_dims(u, obs, act, env_id)
    out = np.empty(len(obs))
    for i in range(len(obs)):
        _set_from_obs(u, obs[i])
        _, reward, *_ = u.step(act[i])
        out[i] = reward
    return torch.from_numpy(out).float().reshape(*lead, 1)


def replay_locomotion_actions(env_name: str, first_observation: torch.Tensor,
                              actions: list[torch.Tensor | np.ndarray]) -> list[dict[str, np.ndarray | bool]]:
    """Open-loop replays: each action sequence run from the state rebuilt from its first observation.

    The env's own ``step`` gives the rewards and its termination (Hopper / Walker2d end when unhealthy); a
    replay stops there or when its actions run out. Actions are clipped to the action box ``[-1, 1]``.

    Args:
        env_name: locomotion env (see :func:`locomotion_env_id`).
        first_observation: ``[N, obs_dim]`` start of each trajectory.
        actions: ``N`` sequences ``[L_i, act_dim]``.

    Returns:
        One dict per trajectory: ``"reward"`` ``[n_i]``, ``"observation"`` ``[n_i + 1, obs_dim]`` (the start,
        then each next observation), ``"terminated"`` (the env ended it, at its last step ``n_i``).

    Example:
        >>> env = make_locomotion_env("hopper", seed=0)
        >>> td = env.rollout(5)
        >>> ep = replay_locomotion_actions("hopper", td["observation"][:1], [td["action"]])[0]
        >>> bool(np.allclose(ep["reward"], td["next", "reward"].squeeze(-1).numpy(), atol=1e-4)), ep["terminated"]
        (True, False)
    """
    env_id = locomotion_env_id(env_name)
    u = _sim(env_id)
    obs, _ = _flat(first_observation, "first_observation")
    if len(actions) != len(obs):
        raise ValueError(f"replay_locomotion_actions: {len(obs)} first observations but {len(actions)} action sequences")
    out = []
    for o, a in zip(obs, actions):
        act, _ = _flat(a, "actions")
        _check_dims(u, o[None], act[:1] if len(act) else np.zeros((1, u.model.nu)), env_id)
        out.append(_run_episode(u, o, len(act), lambda t, act=act: np.clip(act[t], -1.0, 1.0)))
    return out


def _run_episode(u, first_observation: np.ndarray | None, steps: int, choose) -> dict[str, np.ndarray | bool]:
    """One episode from the state rebuilt from ``first_observation`` (``None``: from the simulator's current state):
    ``u.step(choose(t))`` for ``t < steps``, until the env terminates it (the one simulator loop of
    :func:`replay_locomotion_actions`, :func:`track_locomotion_paths` and ``bench/locomotion_fidelity.py``; ``choose``
    may read the simulator's current state)."""
    if first_observation is not None:
        _set_from_obs(u, first_observation)
    rewards, states, terminated = [], [u._get_obs()], False
    for t in range(steps):
        nxt, reward, terminated, _, _ = u.step(choose(t))
        rewards.append(reward)
        states.append(nxt)
        if terminated:
            break
    return {"reward": np.asarray(rewards, np.float64), "observation": np.stack(states), "terminated": bool(terminated)}


def track_locomotion_paths(env_name: str, paths: torch.Tensor, actions: torch.Tensor, lengths: list[int], *,
                           scale: torch.Tensor | np.ndarray | None = None, candidates: int = 64, noise: float = 0.3,
                           uniform: float = 0.5, lookahead: int = 1, seed: int = 0
                           ) -> list[dict[str, np.ndarray | bool]]:
    """Closed-loop tracking of observation paths with the simulator as the model: a shooting controller.

    From the state rebuilt from a path's first observation, every step tries ``candidates`` actions (the path's
    own action; of the other ``candidates - 1``, the share ``uniform`` drawn uniformly from the action box
    ``[-1, 1]``, the rest Gaussian perturbations of the path's action, std ``noise``, clipped) from the state
    the simulator actually reached, keeps the one whose next observation lands nearest the path's next
    one (distance per dimension divided by ``scale``), and steps the env with it (its reward and termination).
    With ``lookahead = L > 1`` each candidate is scored over the next ``L`` steps instead: after its first
    action it applies the path's own next actions shifted by the same offset (clipped), and the distances to
    the path's next ``L`` observations are summed (random shooting; a greedy one-step tracker can pick an
    action that lands on the next observation from a state that cannot follow the rest). Only the first
    action is executed. The last step, with no next observation to aim at, takes the path's own action. A path
    the simulator can follow (a recorded one) is reproduced exactly: its own actions land on it.

    Args:
        env_name: locomotion env (see :func:`locomotion_env_id`).
        paths: ``[N, H, obs_dim]`` observations; ``actions``: ``[N, H, act_dim]`` (the candidates' centre).
        lengths: valid steps of each path.
        scale: ``[obs_dim]`` per-dimension scale of the distance (e.g. the data's std); default 1.
        candidates: actions tried per step (>= 1).
        noise: std of the perturbations.
        uniform: share of the other candidates drawn uniformly from the action box (any action, not only ones
            near the path's own).
        lookahead: steps each candidate is scored over (>= 1; 1: greedy one-step tracking).
        seed: seeds the perturbations, per path together with the path's own numbers (a CRC of its valid
            observations and actions), so a path's reading depends on the path alone, not on the paths tracked
            with it or before it: a trajectory in both the top-k and the final set reads the same in both.

    Returns:
        One dict per path: ``"reward"`` ``[n_i]``, ``"observation"`` ``[n_i + 1, obs_dim]``, ``"terminated"``
        (the env ended it) and ``"path_error"`` ``[n_i - 1]`` (scaled distance to the path's next observation).

    Example:
        >>> env = make_locomotion_env("hopper", seed=0)
        >>> td = env.rollout(6)
        >>> ep = track_locomotion_paths("hopper", td["observation"][None], td["action"][None], [6], candidates=8)[0]
        >>> bool(np.allclose(ep["reward"], td["next", "reward"].squeeze(-1).numpy(), atol=1e-4))
        True
    """
    if candidates < 1 or not 0.0 <= uniform <= 1.0 or lookahead < 1:
        raise ValueError(f"track_locomotion_paths: need candidates >= 1, uniform in [0, 1] and lookahead >= 1, got "
                         f"{candidates}, {uniform}, {lookahead}")
    num_uniform = int(round(uniform * (candidates - 1)))
    env_id = locomotion_env_id(env_name)
    u = _sim(env_id)
    paths_np = paths.detach().cpu().double().numpy() if isinstance(paths, torch.Tensor) else np.asarray(paths, float)
    acts = actions.detach().cpu().double().numpy() if isinstance(actions, torch.Tensor) else np.asarray(actions, float)
    if paths_np.ndim != 3 or acts.shape[:2] != paths_np.shape[:2] or len(lengths) != paths_np.shape[0]:
        raise ValueError(f"track_locomotion_paths: paths {list(paths_np.shape)}, actions {list(acts.shape)} and "
                         f"{len(lengths)} lengths do not match ([N, H, obs], [N, H, act], N)")
    _check_dims(u, paths_np[:, 0], acts[:, 0], env_id)
    inv_scale = 1.0 / (np.ones(paths_np.shape[-1]) if scale is None else np.asarray(scale, np.float64))

    def controller(path: np.ndarray, act: np.ndarray, n: int, rng: np.random.Generator):
        def choose(t: int) -> np.ndarray:
            action = np.clip(act[t], -1.0, 1.0)
            if t + 1 >= n or candidates == 1:
                return action
            tries = np.concatenate([
                action[None], rng.uniform(-1.0, 1.0, (num_uniform, action.shape[-1])),
                np.clip(action + noise * rng.standard_normal((candidates - 1 - num_uniform, action.shape[-1])),
                        -1.0, 1.0)])

            def rollout(j: int, a: np.ndarray) -> float:
                dist = 0.0
                for k in range(min(lookahead, n - 1 - t)):
                    u.do_simulation(a if k == 0 else np.clip(act[t + k] + a - action, -1.0, 1.0), u.frame_skip)
                    dist += np.linalg.norm((u._get_obs() - path[t + 1 + k]) * inv_scale)
                return dist

            return tries[shoot(u, tries, rollout)]

        return choose

    out = []
    for path, act, n in zip(paths_np, acts, lengths):
        rng = np.random.default_rng((seed, zlib.crc32(path[:n].tobytes() + act[:n].tobytes())))
        ep = _run_episode(u, path[0], int(n), controller(path, act, int(n), rng))
        reached = min(len(ep["observation"]), int(n))  # the steps that have a path observation to compare with
        ep["path_error"] = np.linalg.norm((ep["observation"][1:reached] - path[1:reached]) * inv_scale, axis=-1)
        out.append(ep)
    return out
