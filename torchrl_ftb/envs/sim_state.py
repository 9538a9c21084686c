"""Save and restore a MuJoCo simulator's integration state, for shooting trackers that try several actions
from one state (:func:`~torchrl_ftb.envs.track_locomotion_paths`,
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
