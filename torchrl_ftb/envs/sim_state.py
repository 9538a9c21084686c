"""Save and restore a MuJoCo simulator's integration state, and the one shooting step built on it, for the
trackers that try several actions from one state (:func:`~torchrl_ftb.envs.track_locomotion_paths`,
:class:`~torchrl_ftb.envs.MetaWorldShootingController`).

Written by hand: a two-line wrapper of ``mujoco.mj_getState`` / ``mj_setState`` that gymnasium's MuJoCo envs
do not expose (their ``set_state`` sets positions and velocities only, not the solver's warm start or the
mocap bodies a Meta-World hand follows, so a restored state would not step the same).

Example:
    >>> import gymnasium as gym
    >>> u = gym.make("Hopper-v5").unwrapped
    >>> _ = u.reset(seed=0)
    >>> saved = save_sim_state(u)
    >>> _ = u.step(u.action_space.sample())
    >>> restore_sim_state(u, saved)
    >>> bool((save_sim_state(u) == saved).all())
    True
"""
from __future__ import annotations

from typing import Callable

import numpy as np


def save_sim_state(u) -> np.ndarray:
    """The simulator's whole integration state (time, positions, velocities, controls, mocap bodies and the
    solver's warm start) of an unwrapped gymnasium MuJoCo env ``u`` (``u.model``, ``u.data``)."""
    import mujoco

    out = np.empty(mujoco.mj_stateSize(u.model, mujoco.mjtState.mjSTATE_INTEGRATION))
    mujoco.mj_getState(u.model, u.data, out, mujoco.mjtState.mjSTATE_INTEGRATION)
    return out


def restore_sim_state(u, state: np.ndarray) -> None:
    """Put ``u``'s simulator back to ``state`` (:func:`save_sim_state`). Derived quantities (body and site
    positions) are stale until the next ``mj_forward`` or step."""
    import mujoco

    mujoco.mj_setState(u.model, u.data, state, mujoco.mjtState.mjSTATE_INTEGRATION)


def shoot(u, tries: np.ndarray, rollout: Callable[[int, np.ndarray], float], *, tolerance: float = 0.0) -> int:
    """One shooting step: run ``rollout(j, tries[j])`` for every candidate action from ``u``'s current simulator
    state (restored before each), and return the index of the one whose distance it returns is least.

    Candidates are kept in order: a later one replaces the kept one only when nearer by more than ``tolerance``,
    so with a tolerance the first candidates win their ties (0: the first least, as ``argmin``). A NaN distance
    (a simulation gone unstable) is never kept; if every distance is NaN, candidate 0 is. The simulator is left
    in the state it was given.

    Example:
        >>> import gymnasium as gym
        >>> u = gym.make("Hopper-v5").unwrapped
        >>> _ = u.reset(seed=0)
        >>> tries = np.stack([np.zeros(3), np.ones(3)])
        >>> def rollout(j, a):
        ...     u.do_simulation(a, u.frame_skip)
        ...     return float(-u.data.qvel[0])  # prefer the faster forward move
        >>> before = save_sim_state(u)
        >>> shoot(u, tries, rollout) in (0, 1), bool((save_sim_state(u) == before).all())
        (True, True)
    """
    saved = save_sim_state(u)
    best, best_dist = 0, np.inf
    for j, a in enumerate(tries):
        restore_sim_state(u, saved)
        dist = float(rollout(j, a))
        if dist < best_dist - tolerance:  # False for NaN
            best, best_dist = j, dist
    restore_sim_state(u, saved)
    return best
