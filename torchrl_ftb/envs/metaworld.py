"""Meta-World v3 environments for TorchRL, scripted experts and a ground-truth reward oracle.

* :func:`make_metaworld_env` — a torchrl env (``GymWrapper`` around ``Meta-World/MT1``)
  with float32 observations and ``("next", "success")`` as bool ``[1]``.
* :func:`scripted_policy` — the task's scripted expert (``metaworld.policies``).
* :func:`metaworld_true_reward` — the true reward/success of (generated) observation and
  action sequences, by driving a simulator along the observed hand path (see its docstring
  for what is exact and what is approximated) and :func:`metaworld_reward_error`, which
  measures that approximation on real transitions whose reward is known.

Example:
    >>> from torchrl_ftb.envs import make_metaworld_env
    >>> env = make_metaworld_env("button-press-v3", seed=0, max_episode_steps=5)
    >>> td = env.rollout(5)
    >>> td["next", "success"].shape, td["observation"].dtype
    (torch.Size([5, 1]), torch.float32)
"""
from __future__ import annotations

import functools
import re
import warnings
from typing import Any, Callable

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite
from torchrl.envs import DoubleToFloat, GymWrapper, TransformedEnv
from torchrl.envs.gym_like import BaseInfoDictReader

from torchrl_ftb.envs.sim_state import shoot

__all__ = [
    "METAWORLD_MAX_EPISODE_STEPS",
    "METAWORLD_OBSERVATION_LAYOUT",
    "SuccessInfoReader",
    "metaworld_tasks",
    "check_metaworld_task",
    "make_metaworld_gym_env",
    "configure_goal",
    "make_metaworld_env",
    "scripted_policy",
    "metaworld_true_reward",
    "metaworld_reward_error",
    "metaworld_frame_stack_error",
    "metaworld_frame_stack_check",
    "fit_metaworld_hand_model",
    "metaworld_hand_model_error",
    "metaworld_hand_model_check",
    "fit_metaworld_contact_reach",
    "metaworld_contactless_object_path",
    "metaworld_contact_check",
    "metaworld_closest_approach",
    "metaworld_hand_penetration",
    "metaworld_penetration_check",
    "metaworld_hand_steps",
    "metaworld_max_hand_step",
    "metaworld_hand_step_check",
    "METAWORLD_PHYSICS_PROXIES",
    "metaworld_physics_errors",
    "physics_limit",
    "MetaWorldShootingController",
]

METAWORLD_MAX_EPISODE_STEPS = 500

#: Structure of a v3 observation (39 = current frame 0:18, previous frame 18:36, goal 36:39):
#: ``obs[t, 18 + i] = obs[t - 1, i]`` and a goal constant within an episode. Keyword arguments
#: of :func:`torchrl_ftb.diffusion.make_diffuser` (``lagged_dims``, ``time_constant_dims``).
METAWORLD_OBSERVATION_LAYOUT = {
    "lagged_dims": tuple((18 + i, i) for i in range(18)),
    "time_constant_dims": (36, 37, 38),
}


def _quiet_metaworld() -> None:
    # Meta-World observations leave their declared bounds (dims 36-38) and gymnasium's
    # passive checker warns on every step; the warnings carry no information for us.
    warnings.filterwarnings("ignore", message=".*is not within the observation space.*")
    warnings.filterwarnings("ignore", message=".*Box observation space maximum and minimum.*")
    warnings.filterwarnings("ignore", message=".*env.get_wrapper_attr.*")


@functools.lru_cache(maxsize=1)
def metaworld_tasks() -> tuple[str, ...]:
    """Meta-World v3 task names that have a scripted expert policy (sorted).

    Example:
        >>> "button-press-v3" in metaworld_tasks()
        True
    """
    import metaworld
    from metaworld.policies import ENV_POLICY_MAP

    return tuple(sorted(set(metaworld.MT1.ENV_NAMES) & set(ENV_POLICY_MAP)))


def check_metaworld_task(task: str) -> str:
    """Return ``task`` if it is a v3 task with a scripted policy, else raise ``ValueError``."""
    tasks = metaworld_tasks()
    if task not in tasks:
        raise ValueError(f"unknown Meta-World task {task!r}; valid v3 tasks: {', '.join(tasks)}")
    return task


def scripted_policy(task: str) -> Callable[[np.ndarray], np.ndarray]:
    """The scripted expert of a Meta-World v3 task: ``policy(obs) -> action`` (numpy, 4-d).

    The policy reads a *copy* of ``obs``: some of Meta-World's scripted policies shift parsed
    positions in place (``door-open-v3``: ``pos_door[0] -= 0.05``; ``door-close-v3``:
    ``pos_door += ...``), which would silently rewrite the caller's observation — in a
    dataset, the recorded object position of every step.

    Example:
        >>> pi = scripted_policy("door-close-v3")
        >>> obs = np.zeros(39)
        >>> pi(obs).shape, bool((obs == 0).all())
        ((4,), True)
    """
    from metaworld.policies import ENV_POLICY_MAP

    get_action = ENV_POLICY_MAP[check_metaworld_task(task)]().get_action

    def policy(obs: np.ndarray) -> np.ndarray:
        return get_action(np.array(obs, copy=True))

    return policy


def _find_wrapper(env, name: str):
    e = env
    while e is not None:
        if type(e).__name__ == name:
            return e
        e = getattr(e, "env", None)
    return None


def configure_goal(gym_env, *, random_goal: bool, seed: int) -> None:
    """Fix or randomise the goal of a ``Meta-World/MT1`` gymnasium env (in place).

    ``random_goal=False``: every reset uses the first of MT1's goals for ``seed`` (so an env
    and the dataset's expert group built with the same seed share their goal).
    ``random_goal=True``: each reset draws a fresh goal/object placement from the task's
    random-reset space with a generator seeded by ``seed`` (Meta-World's own rejection
    sampling applies). MT1's own "pick one of 50 goals" resampling is switched off.
    """
    u = gym_env.unwrapped
    select = _find_wrapper(gym_env, "RandomTaskSelectWrapper")
    select.toggle_sample_tasks_on_reset(False)
    u.set_task(select.tasks[0])
    if random_goal:
        u._freeze_rand_vec = False
        u.seeded_rand_vec = True
        u.np_random = np.random.default_rng(seed)


def _set_time_limit(gym_env, max_episode_steps: int) -> None:
    u = gym_env.unwrapped
    u.max_path_length = max(int(max_episode_steps), METAWORLD_MAX_EPISODE_STEPS)
    limit = _find_wrapper(gym_env, "TimeLimit")
    limit._max_episode_steps = int(max_episode_steps)


def make_metaworld_gym_env(task: str, *, seed: int = 0, max_episode_steps: int = 500,
                           random_goal: bool = False):
    """The plain gymnasium ``Meta-World/MT1`` env for ``task`` with goal mode and time limit set.

    Used by :func:`make_metaworld_env` and by the dataset generator (which drives the raw env
    for speed).
    """
    import gymnasium as gym
    import metaworld  # noqa: F401  (registers the Meta-World/* ids)

    check_metaworld_task(task)
    if max_episode_steps < 1:
        raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
    _quiet_metaworld()
    env = gym.make("Meta-World/MT1", env_name=task, seed=int(seed))
    configure_goal(env, random_goal=random_goal, seed=int(seed))
    _set_time_limit(env, max_episode_steps)
    return env


class SuccessInfoReader(BaseInfoDictReader):
    """Reads Meta-World's ``info["success"]`` (a Python float) as a bool ``[1]`` entry.

    ``default_info_dict_reader`` crashes on Meta-World's Python floats, hence this reader.

    Example:
        >>> from tensordict import TensorDict
        >>> SuccessInfoReader()({"success": 1.0}, TensorDict())["success"]
        tensor([True])
    """

    def __init__(self, key: str = "success"):
        self.key = key
        self._spec = Composite({key: Categorical(2, shape=(1,), dtype=torch.bool)}, shape=[])

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        value = bool(info_dict.get(self.key, 0.0)) if info_dict else False
        tensordict.set(self.key, torch.tensor([value], dtype=torch.bool, device=tensordict.device))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._spec


class _MetaWorldGymWrapper(GymWrapper):
    """``GymWrapper`` whose ``set_seed`` also seeds the goal draws (:func:`configure_goal`): Meta-World's
    ``reset(seed=)`` leaves them alone, so the sub-envs of a ``SerialEnv`` (seeded one after another by torchrl)
    would all draw the same goals. The goals are seeded before the reset ``set_seed`` runs, so an env
    seeded again with the seed it was built with draws what it drew before."""

    def __init__(self, env, *, random_goal: bool, **kwargs) -> None:
        self._random_goal = bool(random_goal)
        super().__init__(env, **kwargs)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            configure_goal(self._env, random_goal=self._random_goal, seed=int(seed))
        super()._set_seed(seed)


def make_metaworld_env(
    task: str,
    *,
    seed: int = 0,
    max_episode_steps: int = 500,
    device: str | torch.device = "cpu",
    random_goal: bool = False,
):
    """A TorchRL Meta-World v3 env with float32 observations and ``("next", "success")``.

    Args:
        task: a v3 task name, e.g. ``"button-press-v3"`` (see :func:`metaworld_tasks`).
        seed: seeds the goal list, the env and (if ``random_goal``) the goal draws; ``env.set_seed(s)``
            seeds the goal draws again (so the sub-envs of a ``SerialEnv`` draw different goals).
        max_episode_steps: time limit (truncation); Meta-World's default is 500.
        device: torch device of the env's outputs.
        random_goal: draw a new goal at every reset (else a fixed goal, see
            :func:`configure_goal`).

    Returns:
        A ``TransformedEnv(GymWrapper(...), DoubleToFloat())``.

    Raises:
        ValueError: unknown task (the message lists the valid ones).

    Example:
        >>> env = make_metaworld_env("drawer-open-v3", max_episode_steps=3)
        >>> env.rollout(3)["next", "observation"].shape
        torch.Size([3, 39])
    """
    gym_env = make_metaworld_gym_env(task, seed=seed, max_episode_steps=max_episode_steps,
                                     random_goal=random_goal)
    base = _MetaWorldGymWrapper(gym_env, random_goal=random_goal, device=device)
    base.set_info_dict_reader(SuccessInfoReader())
    env = TransformedEnv(base, DoubleToFloat())
    env.set_seed(int(seed))
    # set_seed's reset drew a goal from the generator it seeded: restart it, so the first episode draws the first
    configure_goal(gym_env, random_goal=random_goal, seed=int(seed))
    return env


# --------------------------------------------------------------------------------------
# ground-truth reward of observation/action sequences
# --------------------------------------------------------------------------------------
class _SequenceRewarder:
    """Replays an observation sequence in a Meta-World simulator to evaluate its reward.

    What is matched: the reset (object/goal placement) is fitted to the first observation
    through the task's random-reset vector (a linear least-squares fit, exact for the tasks
    whose placement is affine in that vector); the hand follows the observed hand positions
    (each step the mocap target is re-anchored at the observed hand plus the simulator's
    current mocap lead, then moved by the action like the env does); the gripper is driven by
    the action; the goal (``_target_pos``) is taken from ``obs[-3:]``. Object poses are read by
    Meta-World's rewards from the observation itself. Not matched: contacts/forces of
    objects that the simulated hand did not move in the same way (grasp-type rewards).
    """

    def __init__(self, task: str):
        self.task = check_metaworld_task(task)
        self.env = make_metaworld_gym_env(task, seed=0)
        self.u = self.env.unwrapped
        self.u.reset()
        self._fit_jacobian()

    def _features(self, obs: np.ndarray) -> np.ndarray:
        return np.concatenate([obs[4:7], obs[11:14], obs[-3:]])

    def _reset_with(self, rand_vec: np.ndarray) -> np.ndarray:
        u = self.u
        u._freeze_rand_vec = False
        u.seeded_rand_vec = True
        u.np_random = _FirstThenRandom(rand_vec)
        obs, _ = u.reset()
        return obs

    def _fit_jacobian(self) -> None:
        space = self.u._random_reset_space
        self.low, self.high = space.low.astype(np.float64), space.high.astype(np.float64)
        self.center = 0.5 * (self.low + self.high)
        f0 = self._features(self._reset_with(self.center))
        cols = []
        for i in range(self.center.size):
            d = np.zeros_like(self.center)
            d[i] = max(1e-3, 0.25 * (self.high[i] - self.low[i]))
            cols.append((self._features(self._reset_with(self.center + d)) - f0) / d[i])
        self.f0, self.jac = f0, np.stack(cols, 1)

    def fit_reset(self, obs0: np.ndarray) -> np.ndarray:
        delta, *_ = np.linalg.lstsq(self.jac, self._features(obs0) - self.f0, rcond=None)
        vec = np.clip(self.center + delta, self.low, self.high)
        return self._reset_with(vec)

    def __call__(self, obs: np.ndarray, act: np.ndarray, next_obs: np.ndarray):
        import mujoco

        u = self.u
        # Meta-World's observation clips the gripper opening (current and stacked previous frame)
        # to [0, 1] and its rewards assume it (``hamacher_product`` raises otherwise); generated
        # observations can leave that range, so project them back as the env would. No-op on real data.
        obs, next_obs = obs.copy(), next_obs.copy()
        for x in (obs, next_obs):
            x[:, [3, 21]] = np.clip(x[:, [3, 21]], 0.0, 1.0)
        self.fit_reset(obs[0])
        mocap_id = u.model.body_mocapid[u.data.body("mocap").id]
        rewards = np.zeros(len(obs))
        success = np.zeros(len(obs), dtype=bool)
        for h in range(len(obs)):
            a = np.clip(act[h].astype(np.float64), -1.0, 1.0)
            lead = u.data.mocap_pos[mocap_id] - u.get_endeff_pos()
            target = obs[h, 0:3] + lead + a[:3] * u.action_scale
            u.data.mocap_pos[mocap_id] = np.clip(target, u.mocap_low, u.mocap_high)
            u.data.mocap_quat[mocap_id] = np.array([1, 0, 1, 0])
            u.do_simulation([a[-1], -a[-1]], n_frames=u.frame_skip)
            mujoco.mj_forward(u.model, u.data)
            u._target_pos = next_obs[h, -3:].astype(np.float64).copy()
            for site in u._target_site_config:
                u._set_pos_site(*site)
            r, info = u.evaluate_state(next_obs[h].astype(np.float64), a)
            rewards[h] = float(r)
            success[h] = bool(info["success"])
        return rewards, success


class _FirstThenRandom:
    """Stand-in for ``np_random`` at reset: yields the fitted reset vector first, then random
    draws (so Meta-World's rejection loops still terminate if the fitted vector is rejected)."""

    def __init__(self, first: np.ndarray):
        self.first = np.asarray(first, dtype=np.float64)
        self.rng = np.random.default_rng(0)

    def uniform(self, low, high, size=None):
        if self.first is not None:
            out, self.first = self.first, None
            return out
        return self.rng.uniform(low, high, size=size)


@functools.lru_cache(maxsize=8)
def _rewarder(task: str) -> _SequenceRewarder:
    return _SequenceRewarder(task)


def _as_batch(x: torch.Tensor | np.ndarray, name: str, dim: int) -> np.ndarray:
    x = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    if x.ndim not in (2, 3) or x.shape[-1] != dim:
        raise ValueError(f"{name}: expected shape [H, {dim}] or [N, H, {dim}], got {list(x.shape)}")
    return x[None] if x.ndim == 2 else x


def metaworld_true_reward(
    task: str,
    observation: torch.Tensor,
    action: torch.Tensor,
    *,
    next_observation: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ground-truth Meta-World reward and success of observation/action sequences.

    Meta-World's reward of step ``h`` is ``evaluate_state(s_{h+1}, a_h)`` on the *next*
    observation; it also reads simulator quantities (finger positions, initial gripper
    position, reset placement). A simulator is therefore driven along the sequence (see
    :class:`_SequenceRewarder`): exact up to the hand-tracking and contact approximations,
    whose error :func:`metaworld_reward_error` measures on real transitions.

    Args:
        task: v3 task name.
        observation: ``[H, 39]`` or ``[N, H, 39]`` states ``s_h``.
        action: ``[H, 4]`` or ``[N, H, 4]`` actions ``a_h``.
        next_observation: ``s_{h+1}``; if ``None`` the sequence is shifted by one step and
            the last (valid) step reuses its own observation (an approximation on that step only;
            padding is never read).
        mask: optional ``[N, H]`` valid-step mask; padded steps get reward 0 / False.

    Returns:
        ``(reward, success)`` shaped ``[..., H, 1]`` (float32 / bool), like the inputs.

    Example:
        >>> obs, act = torch.zeros(3, 39), torch.zeros(3, 4)
        >>> r, s = metaworld_true_reward("button-press-v3", obs, act)
        >>> r.shape, s.dtype
        (torch.Size([3, 1]), torch.bool)
    """
    squeeze = observation.ndim == 2
    obs = _as_batch(observation, "observation", 39)
    act = _as_batch(action, "action", 4)
    nxt = None if next_observation is None else _as_batch(next_observation, "next_observation", 39)
    if act.shape[:2] != obs.shape[:2] or (nxt is not None and nxt.shape != obs.shape):
        raise ValueError(
            f"observation {list(obs.shape)}, action {list(act.shape)} and next_observation "
            f"{None if nxt is None else list(nxt.shape)} do not share [N, H]"
        )
    n, h = obs.shape[:2]
    m = np.ones((n, h), dtype=bool) if mask is None else _mask_np(mask, n, h)
    rewards = np.zeros((n, h), dtype=np.float32)
    success = np.zeros((n, h), dtype=bool)
    rewarder = _rewarder(task)
    for i in range(n):
        length = int(m[i].sum())
        if length == 0:
            continue
        o = obs[i, :length]
        # shifted within the valid prefix: the last valid step's next state is its own, not padding
        o_next = np.concatenate([o[1:], o[-1:]], 0) if nxt is None else nxt[i, :length]
        r, s = rewarder(o, act[i, :length], o_next)
        rewards[i, :length], success[i, :length] = r, s
    r_t, s_t = torch.from_numpy(rewards)[..., None], torch.from_numpy(success)[..., None]
    return (r_t[0], s_t[0]) if squeeze else (r_t, s_t)


def _mask_np(mask, n: int, h: int) -> np.ndarray:
    m = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    m = m.reshape(-1, m.shape[-1]) if m.ndim == 1 else m
    if m.shape != (n, h):
        raise ValueError(f"mask: expected shape [{n}, {h}], got {list(m.shape)}")
    return m.astype(bool)


def metaworld_reward_error(
    task: str,
    trajectories: TensorDictBase,
    *,
    use_next_observation: bool = True,
) -> dict[str, float]:
    """Error of :func:`metaworld_true_reward` on real transitions whose reward is known.

    Args:
        task: v3 task name the data come from.
        trajectories: ``[N, H]`` trajectory batch with ``("next", "reward")`` (and
            ``("next", "observation")``; ``("next", "success")`` optional).
        use_next_observation: score with the recorded next observations (``True``) or with
            the shifted observation sequence (what a generated trajectory provides).

    Returns:
        ``{"reward_mae", "reward_max_abs", "return_mae", "return_rel_mae",
        "success_agreement", "num_steps"}`` (per-step and per-trajectory errors; the
        return error is relative to the mean absolute true return).

    Example:
        >>> from torchrl_ftb.datasets import make_metaworld_dataset  # doctest: +SKIP
        >>> td, _ = make_metaworld_dataset("button-press-v3", episodes_per_group=2)  # doctest: +SKIP
        >>> metaworld_reward_error("button-press-v3", td[:4])["reward_mae"] < 0.5  # doctest: +SKIP
        True
    """
    if ("next", "reward") not in trajectories.keys(True):
        raise ValueError("trajectories: missing ('next', 'reward') — the error needs the true reward")
    mask = trajectories.get("mask")
    nxt = trajectories.get(("next", "observation")) if use_next_observation else None
    r, s = metaworld_true_reward(task, trajectories.get("observation"), trajectories.get("action"),
                                 next_observation=nxt, mask=mask)
    true_r = trajectories.get(("next", "reward")).float()
    diff = (r - true_r).squeeze(-1).abs()[mask]
    ret, true_ret = (r.squeeze(-1) * mask).sum(-1), (true_r.squeeze(-1) * mask).sum(-1)
    out = {
        "reward_mae": float(diff.mean()),
        "reward_max_abs": float(diff.max()),
        "return_mae": float((ret - true_ret).abs().mean()),
        "return_rel_mae": float((ret - true_ret).abs().mean() / true_ret.abs().mean().clamp_min(1e-8)),
        "num_steps": int(mask.sum()),
    }
    if ("next", "success") in trajectories.keys(True):
        true_s = trajectories.get(("next", "success")).squeeze(-1)[mask]
        out["success_agreement"] = float((s.squeeze(-1)[mask] == true_s).float().mean())
    return out


def _metaworld_steps(trajectories: TensorDictBase, what: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The (checked) 39-d ``observation`` ``[N, H, 39]`` and the ``[N, H - 1]`` mask of pairs of
    consecutive valid steps, which every Meta-World dynamics proxy below is a mean over."""
    obs, mask = trajectories.get("observation"), trajectories.get("mask").bool()
    if obs.shape[-1] != 39:
        raise ValueError(f"{what}: 'observation' has {obs.shape[-1]} dims; "
                         "Meta-World v3 observations have 39 (two stacked 18-d frames + 3-d goal)")
    return obs, mask[:, 1:] & mask[:, :-1]


def _mean_over_steps(err: torch.Tensor, pair: torch.Tensor, *, pooled: bool) -> torch.Tensor:
    """Per-transition errors ``[N, H - 1]`` (0 off ``pair``) -> ``[N]`` means (0 with no transition),
    or with ``pooled`` one mean over all transitions (NaN with none)."""
    if pooled:
        return err.sum() / pair.sum() if bool(pair.any()) else torch.tensor(float("nan"))
    return err.sum(-1) / pair.sum(-1).clamp_min(1)


def metaworld_frame_stack_error(trajectories: TensorDictBase, *, pooled: bool = False) -> torch.Tensor:
    """Frame-stack consistency of Meta-World (generated) trajectories, in metres.

    A v3 observation stacks the previous frame: ``obs[t + 1, 18:36]`` must equal
    ``obs[t, 0:18]`` (hand, gripper and object poses). Real data meet this to float precision;
    a generated trajectory's error measures how far its consecutive steps are from one
    another's copy. The error of a transition is the Euclidean norm over the 18 stacked
    coordinates; only pairs of consecutive valid steps count.

    Args:
        trajectories: ``[N, H]`` batch with a 39-d ``observation`` and a ``mask``.
        pooled: return one number, the mean over all transitions of the batch (longer
            trajectories weigh more), instead of one mean per trajectory.

    Returns:
        ``[N]`` per-trajectory mean error (0 for trajectories with < 2 valid steps), or a
        scalar with ``pooled=True`` (NaN if the batch has no transition).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(1, 3, 39)
        >>> obs[0, 1, 18:21] = torch.tensor([0.003, 0.0, 0.004])  # 5 mm off the previous frame
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(1, 3, dtype=torch.bool)}, [1, 3])
        >>> round(float(metaworld_frame_stack_error(td)[0]), 4)  # two transitions: 5 mm and 0
        0.0025
    """
    obs, pair = _metaworld_steps(trajectories, "metaworld_frame_stack_error")
    err = (obs[:, 1:, 18:36].float() - obs[:, :-1, 0:18].float()).norm(dim=-1) * pair
    return _mean_over_steps(err, pair, pooled=pooled)


def _consecutive_pairs(trajectories: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``obs[t]``, ``a[t]``, ``obs[t+1]`` (float64, each ``[N, H - 1, .]``) and the ``[N, H - 1]`` mask
    of the pairs of consecutive valid steps."""
    obs, pair = _metaworld_steps(trajectories, "Meta-World hand model")
    obs, act = obs.double(), trajectories.get("action").double()
    return obs[:, :-1], act[:, :-1], obs[:, 1:], pair


def _hand_features(obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    return torch.cat([obs, act, torch.ones_like(obs[..., :1])], -1)


def fit_metaworld_hand_model(trajectories: TensorDictBase, *, ridge: float = 1e-6) -> torch.Tensor:
    """Linear one-step model of the Meta-World hand, fitted on real trajectories.

    A dynamics proxy for generated trajectories (Meta-World has no one-step oracle that takes
    an arbitrary observation): the hand displacement ``obs[t+1, 0:3] - obs[t, 0:3]`` is regressed
    on ``[obs[t], a[t], 1]`` by ridge regression. The hand is mocap-driven (the action moves its
    target by ``a[:3] / 100``), so on real data the residual is about a millimetre
    (``bench/diffusion_quality.py``); :func:`metaworld_hand_model_error` measures it on
    generated trajectories.

    Args:
        trajectories: ``[N, H]`` real trajectories with 39-d ``observation``, ``action`` and ``mask``.
        ridge: L2 penalty of the least-squares fit.

    Returns:
        ``[44, 3]`` float64 weights.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs, act = torch.zeros(1, 4, 39), torch.full((1, 4, 4), 0.5)
        >>> obs[0, :, 0] = torch.arange(4) * 0.005  # the hand moves 5 mm per step
        >>> td = TensorDict({"observation": obs, "action": act, "mask": torch.ones(1, 4, dtype=torch.bool)}, [1, 4])
        >>> w = fit_metaworld_hand_model(td)
        >>> round(float(metaworld_hand_model_error(td, w)[0]), 6)
        0.0
    """
    o, a, o1, pair = _consecutive_pairs(trajectories)
    if not bool(pair.any()):
        raise ValueError("fit_metaworld_hand_model: no pair of consecutive valid steps to fit on")
    x, y = _hand_features(o[pair], a[pair]), (o1[pair][:, :3] - o[pair][:, :3])
    eye = torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
    return torch.linalg.solve(x.T @ x + ridge * eye, x.T @ y)


def metaworld_hand_model_error(trajectories: TensorDictBase, weights: torch.Tensor, *,
                               pooled: bool = False) -> torch.Tensor:
    """Residual of :func:`fit_metaworld_hand_model` on (generated) trajectories, in metres.

    The error of a transition is the Euclidean norm of the predicted minus the observed hand
    displacement; only pairs of consecutive valid steps count. With
    ``METAWORLD_OBSERVATION_LAYOUT`` the diffuser makes the frame stack exact by construction,
    so this is the proxy left that tells a physically possible hand path from an impossible one.

    Args:
        trajectories: ``[N, H]`` batch with 39-d ``observation``, ``action`` and ``mask``.
        weights: ``[44, 3]`` from :func:`fit_metaworld_hand_model`.
        pooled: one number over all transitions instead of one mean per trajectory.

    Returns:
        ``[N]`` per-trajectory mean error (0 with < 2 valid steps), or a scalar with
        ``pooled=True`` (NaN if the batch has no transition).
    """
    o, a, o1, pair = _consecutive_pairs(trajectories)
    pred = _hand_features(o, a) @ weights.to(o)
    err = ((o1[..., :3] - o[..., :3]) - pred).norm(dim=-1) * pair
    return _mean_over_steps(err, pair, pooled=pooled).float()


def _at_most(proxy: Callable[[TensorDictBase], torch.Tensor], limit: float, *, what: str,
             name: str) -> Callable[[TensorDictBase], torch.Tensor]:
    """A flow validity check from a ``[N]`` proxy: True where ``proxy(trajectories) <= limit`` (metres)."""
    if not limit >= 0:
        raise ValueError(f"{name}: {what} must be >= 0 metres, got {limit}")

    def check(trajectories: TensorDictBase) -> torch.Tensor:
        return proxy(trajectories) <= limit

    return check


def metaworld_frame_stack_check(max_error: float) -> Callable[[TensorDictBase], torch.Tensor]:
    """A flow validity check: ``[N]`` True where the mean frame-stack error is ``<= max_error`` m.

    For :class:`torchrl_ftb.flow.FlowToBetter` (``validity_fn``): rejects generated trajectories
    whose consecutive steps are not copies of one another (:func:`metaworld_frame_stack_error`),
    i.e. physically inconsistent samples that the simulator's reward can still score highly.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(2, 3, 39)
        >>> obs[1, 1, 18:21] = 0.1  # the second trajectory's stacked frame is 17 cm off
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(2, 3, dtype=torch.bool)}, [2, 3])
        >>> metaworld_frame_stack_check(0.02)(td).tolist()
        [True, False]
    """
    return _at_most(metaworld_frame_stack_error, max_error, what="max_error", name="metaworld_frame_stack_check")


def metaworld_hand_model_check(weights: torch.Tensor, max_error: float) -> Callable[[TensorDictBase], torch.Tensor]:
    """A flow validity check: ``[N]`` True where the hand path meets the one-step hand model.

    For :class:`torchrl_ftb.flow.FlowToBetter` (``validity_fn``): rejects generated trajectories
    whose hand moves in a way the actions cannot explain (:func:`metaworld_hand_model_error`
    above ``max_error`` metres; real data: about 1 mm). The frame-stack check's counterpart for
    samples whose stack is exact by construction (``METAWORLD_OBSERVATION_LAYOUT``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs, act = torch.zeros(2, 4, 39), torch.full((2, 4, 4), 0.5)
        >>> obs[:, :, 0] = torch.arange(4) * 0.005
        >>> td = TensorDict({"observation": obs, "action": act, "mask": torch.ones(2, 4, dtype=torch.bool)}, [2, 4])
        >>> w = fit_metaworld_hand_model(td)
        >>> td["observation"][1, 2, 0] += 0.05  # the second hand jumps 5 cm and back
        >>> metaworld_hand_model_check(w, 0.01)(td).tolist()
        [True, False]
    """
    return _at_most(lambda trajectories: metaworld_hand_model_error(trajectories, weights), max_error,
                    what="max_error", name="metaworld_hand_model_check")


def physics_limit(spec: float | str, real: torch.Tensor, *, field: str) -> float:
    """A physics-check limit in metres, absolute or relative to real data.

    A number is the limit itself. A string ``"<f>x"`` (e.g. ``"1.5x"``) is ``f`` times the
    largest value the proxy takes on ``real``, the dataset's own trajectories: ``"1x"`` accepts
    no sample that is further off than the worst real trajectory. A relative limit follows the
    task and the proxy's fit (real hand-model errors are 1.8-2.4 mm by task, BENCHMARKS #5),
    where an absolute one tuned on one task may be loose on another.

    Args:
        spec: metres (``>= 0``) or ``"<f>x"`` with ``f >= 0``.
        real: ``[N]`` the proxy on real trajectories (e.g. :func:`metaworld_hand_model_error`
            of the dataset); read only for a relative ``spec``.
        field: the config field, named in errors.

    Example:
        >>> import torch
        >>> physics_limit(0.01, torch.tensor([0.001, 0.002]), field="max_error")
        0.01
        >>> round(physics_limit("1.5x", torch.tensor([0.001, 0.002]), field="max_error"), 6)
        0.003
    """
    relative = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*x\s*", spec) if isinstance(spec, str) else None
    if relative is not None:
        if real.numel() == 0 or not bool(torch.isfinite(real).all()):
            raise ValueError(f"{field}={spec!r}: the dataset gives no finite reference value to scale")
        return float(relative.group(1)) * float(real.max())
    try:
        limit = float(spec)
    except (TypeError, ValueError):
        raise ValueError(f"{field}={spec!r}: give metres (a number) or a multiple of the dataset's largest "
                         f"value as '<factor>x', e.g. '1.5x'") from None
    if not limit >= 0:
        raise ValueError(f"{field}={spec!r}: a limit must be >= 0 metres")
    return limit


def metaworld_hand_object_distance(observation: torch.Tensor) -> torch.Tensor:
    """Distance (metres) between the hand (``obs[..., 0:3]``) and the first object (``obs[..., 4:7]``) of
    Meta-World observations ``[..., 39]``.

    Example:
        >>> obs = torch.zeros(2, 39)
        >>> obs[1, 4] = 0.3
        >>> metaworld_hand_object_distance(obs).tolist()
        [0.0, 0.30000001192092896]
    """
    return (observation[..., 0:3] - observation[..., 4:7]).norm(dim=-1)


def _hand_object_steps(trajectories: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per transition ``[N, H - 1]``: the object's displacement (``obs[4:7]``), the smaller hand-object
    distance of its two ends (:func:`metaworld_hand_object_distance`) and the pair mask."""
    obs, pair = _metaworld_steps(trajectories, "Meta-World contact check")
    obs = obs.double()
    obj = obs[..., 4:7]
    dist = metaworld_hand_object_distance(obs)
    return (obj[:, 1:] - obj[:, :-1]).norm(dim=-1), torch.minimum(dist[:, 1:], dist[:, :-1]), pair


def fit_metaworld_contact_reach(trajectories: TensorDictBase, *, quantile: float = 0.99,
                                moving: float = 0.001) -> float:
    """How close the hand is to the object when the object moves, on real Meta-World trajectories.

    Returns the hand-object distance (metres) within which ``quantile`` of the object's motion
    happens (steps where it moves more than ``moving`` m): what "the hand is at the object"
    means for this task (the object's reference point and size differ between tasks).
    :func:`metaworld_contactless_object_path` counts the motion beyond it.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(1, 5, 39)
        >>> obs[0, :, 4] = torch.tensor([0.0, 0.01, 0.02, 0.02, 0.02])  # pushed twice...
        >>> obs[0, :, 0] = obs[0, :, 4] - 0.05  # ...by a hand 5 cm behind it
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(1, 5, dtype=torch.bool)}, [1, 5])
        >>> round(fit_metaworld_contact_reach(td), 3)
        0.05
    """
    step, dist, pair = _hand_object_steps(trajectories)
    sel = pair & (step > moving)
    if not bool(sel.any()):
        raise ValueError("fit_metaworld_contact_reach: the object never moves in these trajectories")
    return float(torch.quantile(dist[sel], quantile))


def metaworld_contactless_object_path(trajectories: TensorDictBase, reach: float) -> torch.Tensor:
    """``[N]`` metres the object moves while the hand is out of ``reach`` (both ends of a step).

    A Meta-World object moves only when the gripper pushes, pulls or carries it, then slides on
    for a little; a generated trajectory that carries the object to its goal while the hand stays
    away -- a high true return the simulator could never produce -- moves it far more than any real
    trajectory does. Calibrate ``reach`` with :func:`fit_metaworld_contact_reach` and the limit with
    this function on real data.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(1, 4, 39)
        >>> obs[0, :, 4] = torch.tensor([0.0, 0.1, 0.2, 0.3])  # the object slides 30 cm, the hand stays at 0
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(1, 4, dtype=torch.bool)}, [1, 4])
        >>> [round(x, 2) for x in metaworld_contactless_object_path(td, reach=0.05).tolist()]
        [0.2]
    """
    step, dist, pair = _hand_object_steps(trajectories)
    return (step * (pair & (dist > reach))).sum(-1).float()


def metaworld_contact_check(reach: float, max_path: float) -> Callable[[TensorDictBase], torch.Tensor]:
    """A flow validity check: ``[N]`` True where the object moves at most ``max_path`` metres while
    the hand is out of ``reach`` (:func:`metaworld_contactless_object_path`).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(2, 4, 39)
        >>> obs[1, :, 4] = torch.tensor([0.0, 0.1, 0.2, 0.3])  # the second object slides off on its own
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(2, 4, dtype=torch.bool)}, [2, 4])
        >>> metaworld_contact_check(reach=0.05, max_path=0.1)(td).tolist()
        [True, False]
    """
    if not reach >= 0:
        raise ValueError(f"metaworld_contact_check: reach must be >= 0 metres, got {reach}")
    return _at_most(lambda trajectories: metaworld_contactless_object_path(trajectories, reach), max_path,
                    what="max_path", name="metaworld_contact_check")


def metaworld_closest_approach(trajectories: TensorDictBase) -> torch.Tensor:
    """``[N]`` the smallest hand-object distance (:func:`metaworld_hand_object_distance`) over each trajectory's
    valid steps, in metres (``inf`` with none).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(1, 3, 39)
        >>> obs[0, :, 4] = torch.tensor([0.2, 0.1, 0.05])  # the object 20, 10, then 5 cm from the hand
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(1, 3, dtype=torch.bool)}, [1, 3])
        >>> [round(x, 3) for x in metaworld_closest_approach(td).tolist()]
        [0.05]
    """
    obs, _ = _metaworld_steps(trajectories, "Meta-World closest approach")
    dist = metaworld_hand_object_distance(obs.double())
    return torch.where(trajectories.get("mask").bool(), dist, torch.inf).amin(-1).float()


def metaworld_hand_penetration(trajectories: TensorDictBase, closest: float) -> torch.Tensor:
    """``[N]`` metres by which each trajectory's hand comes closer to the object than ``closest`` (0 if never).

    Calibrate ``closest`` on real data with :func:`metaworld_closest_approach` (its smallest value): the hand's
    reference point cannot get nearer the object's than the bodies let it, so on real data the penetration is 0
    by construction. A generated path that claims it is nearer puts the hand inside the object (a button, a
    drawer's handle), where the simulator stops it: a closed-loop reading then leaves the path, and the claimed
    return was never reachable (score guidance does this on button-press, BENCHMARKS #5, session 52).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(2, 3, 39)
        >>> obs[:, :, 4] = 0.05
        >>> obs[1, 2, 4] = 0.02  # the second hand ends 2 cm from the object's point
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(2, 3, dtype=torch.bool)}, [2, 3])
        >>> [round(x, 3) for x in metaworld_hand_penetration(td, closest=0.04).tolist()]
        [0.0, 0.02]
    """
    return (float(closest) - metaworld_closest_approach(trajectories)).clamp_min(0)


def metaworld_penetration_check(closest: float, max_depth: float) -> Callable[[TensorDictBase], torch.Tensor]:
    """A flow validity check: ``[N]`` True where the hand comes at most ``max_depth`` metres closer to the object
    than ``closest`` (:func:`metaworld_hand_penetration`; ``closest`` from :func:`metaworld_closest_approach` on the
    dataset, its smallest value).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(2, 3, 39)
        >>> obs[:, :, 4] = 0.05
        >>> obs[1, 2, 4] = 0.02
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(2, 3, dtype=torch.bool)}, [2, 3])
        >>> metaworld_penetration_check(closest=0.04, max_depth=0.005)(td).tolist()
        [True, False]
    """
    if not closest >= 0:
        raise ValueError(f"metaworld_penetration_check: closest must be >= 0 metres, got {closest}")
    return _at_most(lambda trajectories: metaworld_hand_penetration(trajectories, closest), max_depth,
                    what="max_depth", name="metaworld_penetration_check")


def metaworld_hand_steps(trajectories: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-step hand displacement of Meta-World trajectories: ``[N, H - 1]`` metres
    (``|obs[t + 1, 0:3] - obs[t, 0:3]|``, 0 off the mask) and the ``[N, H - 1]`` mask of the pairs of
    consecutive valid steps.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(1, 3, 39)
        >>> obs[0, 1, 0], obs[0, 2, 0] = 0.004, 0.034  # 4 mm, then a 30 mm jump
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(1, 3, dtype=torch.bool)}, [1, 3])
        >>> [round(x, 3) for x in metaworld_hand_steps(td)[0][0].tolist()]
        [0.004, 0.03]
    """
    obs, pair = _metaworld_steps(trajectories, "Meta-World hand step")
    obs = obs.double()
    return (obs[:, 1:, 0:3] - obs[:, :-1, 0:3]).norm(dim=-1) * pair, pair


def metaworld_max_hand_step(trajectories: TensorDictBase) -> torch.Tensor:
    """``[N]`` the largest one-step hand displacement of each trajectory, in metres (0 with < 2 valid steps).

    The hand-model check (:func:`metaworld_hand_model_error`) bounds the *mean* one-step residual, so
    one jump hides in a long plausible path. A sample held at a real start
    (``inpaint_start``) can jump at the seam between the start and what the diffuser made of the rest:
    BENCHMARKS #5 measured a median 27 mm first step where the data's largest step anywhere is 47 mm
    and its median 4 mm. :func:`metaworld_hand_step_check` rejects steps beyond what the data ever does.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(2, 3, 39)
        >>> obs[1, 1:, 0] = 0.06  # the second hand jumps 6 cm once
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(2, 3, dtype=torch.bool)}, [2, 3])
        >>> [round(x, 3) for x in metaworld_max_hand_step(td).tolist()]
        [0.0, 0.06]
    """
    return metaworld_hand_steps(trajectories)[0].amax(-1).float()


def metaworld_hand_step_check(max_step: float) -> Callable[[TensorDictBase], torch.Tensor]:
    """A flow validity check: ``[N]`` True where no step moves the hand more than ``max_step`` metres
    (:func:`metaworld_max_hand_step`; calibrate it on the dataset with :func:`physics_limit`'s ``"1x"``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs = torch.zeros(2, 3, 39)
        >>> obs[1, 1:, 0] = 0.06
        >>> td = TensorDict({"observation": obs, "mask": torch.ones(2, 3, dtype=torch.bool)}, [2, 3])
        >>> metaworld_hand_step_check(0.05)(td).tolist()
        [True, False]
    """
    return _at_most(metaworld_max_hand_step, max_step, what="max_step", name="metaworld_hand_step_check")


#: The names of the three dynamics proxies, in report order: the keys of
#: :func:`metaworld_physics_errors`.
METAWORLD_PHYSICS_PROXIES = ("frame_stack_error", "hand_model_error", "contactless_object_path")


def metaworld_physics_errors(trajectories: TensorDictBase, *, hand_weights: torch.Tensor,
                             reach: float | None) -> dict[str, torch.Tensor]:
    """The three Meta-World dynamics proxies of a batch, ``[N]`` each, in metres:
    ``frame_stack_error``, ``hand_model_error`` and (unless ``reach`` is ``None``)
    ``contactless_object_path`` (:func:`metaworld_frame_stack_error`,
    :func:`metaworld_hand_model_error`, :func:`metaworld_contactless_object_path`).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> obs, act = torch.zeros(1, 4, 39), torch.full((1, 4, 4), 0.5)
        >>> td = TensorDict({"observation": obs, "action": act, "mask": torch.ones(1, 4, dtype=torch.bool)}, [1, 4])
        >>> sorted(metaworld_physics_errors(td, hand_weights=torch.zeros(44, 3), reach=0.1))
        ['contactless_object_path', 'frame_stack_error', 'hand_model_error']
    """
    frame, hand, contact = METAWORLD_PHYSICS_PROXIES
    out = {frame: metaworld_frame_stack_error(trajectories),
           hand: metaworld_hand_model_error(trajectories, hand_weights)}
    if reach is not None:
        out[contact] = metaworld_contactless_object_path(trajectories, reach)
    return out


class MetaWorldShootingController:
    """A closed-loop controller for one observation path in a Meta-World env, with the simulator as its model.

    The Meta-World form of :func:`~torchrl_ftb.envs.track_locomotion_paths`' greedy shooting. Every step it
    tries, from the state the simulator reached, the path's own action at that step, the ``proposal``'s
    action for the observation (e.g. a :meth:`~torchrl_ftb.policy.PathTracker.controller`, which heads for
    the path's hand) and ``candidates - 2`` Gaussian perturbations of the proposal (std ``noise``, clipped to
    ``[-1, 1]``). It keeps the one whose next hand position, gripper opening and object position land nearest
    the path's next observation (``weights`` per part), trying them in that order and replacing the kept one
    only by a candidate nearer by more than ``tolerance`` (m): so the own action wins its ties, and a path the
    simulator can follow (a recorded one, float32-stored) is reproduced exactly, as the locomotion tracker
    reproduces its recorded paths. Past the path's last step it aims at that last observation.

    With ``lookahead = L > 1`` each candidate is scored over the next ``L`` steps instead, as the locomotion
    tracker does: after its first action the path's own next actions shifted by the same offset (clipped), the
    distances to the path's next ``L`` observations summed; only the first action is executed. A greedy choice
    can land on the next observation from a state that cannot follow the rest of the path. Neither reading is
    the path's "true" one where contacts decide the outcome: on 26 generated sweep-into paths, greedy and 5- and
    10-step readings, each following the hand within about 1-2 cm, agreed on success for 14 to 20 of 26
    (BENCHMARKS.md, session 48).

    Hand positions (``obs[0:3]``) and the object's (``obs[4:7]``) are where a Meta-World plan says the
    task happens; the gripper opening (``obs[3]``) is a unitless distance, weighted down by default.

    The episode loop (:func:`~torchrl_ftb.datasets.metaworld.generate_metaworld_episodes`) calls
    :meth:`attach` with its unwrapped env before the first step, then the controller once per step, in order.

    Args:
        path: ``[H, 39]`` observations; ``length``: its valid steps.
        own_actions: ``[H, 4]`` the path's actions (clipped to ``[-1, 1]``).
        proposal: ``obs -> action`` called once per step in order; None: the own action and perturbations
            of it only.
        candidates: actions tried per step (>= 1; 1: the proposal's, or the own action without one, untried).
        noise: std of the perturbations.
        weights: ``(hand, gripper, object)`` weights of the distance to the path's next observation.
        tolerance: how much nearer (weighted metres, summed over the lookahead) a later candidate must land to
            replace an earlier one.
        lookahead: steps each candidate is scored over (>= 1; 1: greedy).
        seed: the perturbations' generator (``numpy.random.default_rng``'s seed; :func:`~torchrl_ftb.analysis.track_paths`
            seeds each path by its own numbers).

    Example:
        >>> import numpy as np
        >>> from torchrl_ftb.datasets.metaworld import generate_metaworld_episodes
        >>> ep = generate_metaworld_episodes("button-press-v3", [(0, 0)], seed=0, noise=0.5, max_steps=20)[0]
        >>> ctrl = MetaWorldShootingController(ep["observation"], len(ep["action"]), own_actions=ep["action"],
        ...                                    candidates=4)
        >>> again = generate_metaworld_episodes("button-press-v3", [(0, 0)], seed=0, noise=0.0, max_steps=20,
        ...                                     controllers=[ctrl])[0]
        >>> bool(np.allclose(again["reward"], ep["reward"]))
        True
    """

    def __init__(self, path: np.ndarray, length: int, *, own_actions: np.ndarray,
                 proposal: Callable[[np.ndarray], np.ndarray] | None = None, candidates: int = 4,
                 noise: float = 0.3, weights: tuple[float, float, float] = (1.0, 0.1, 1.0),
                 tolerance: float = 1e-3, lookahead: int = 1, seed: int | tuple[int, ...] = 0) -> None:
        path, own_actions = np.asarray(path, np.float64), np.asarray(own_actions, np.float64)
        if candidates < 1 or noise < 0 or tolerance < 0 or len(weights) != 3 or lookahead < 1:
            raise ValueError(f"MetaWorldShootingController: need candidates >= 1, noise >= 0, tolerance >= 0, "
                             f"three weights and lookahead >= 1, got {candidates}, {noise}, {tolerance}, {weights}, "
                             f"{lookahead}")
        if path.ndim != 2 or own_actions.ndim != 2 or own_actions.shape[0] != path.shape[0] or not 1 <= length <= len(path):
            raise ValueError(f"MetaWorldShootingController: path {list(path.shape)} and own_actions "
                             f"{list(own_actions.shape)} need one row per step and 1 <= length ({length}) <= {len(path)}")
        self.path, self.length = path, int(length)
        self.own = np.clip(own_actions, -1.0, 1.0)
        self.proposal, self.candidates, self.noise = proposal, int(candidates), float(noise)
        self.weights, self.tolerance = tuple(float(w) for w in weights), float(tolerance)
        self.lookahead = int(lookahead)
        self.rng = np.random.default_rng(seed)
        self.env, self.step = None, 0

    def attach(self, env) -> None:
        """The unwrapped Meta-World env the episode runs in (``model``, ``data``, ``set_xyz_action``)."""
        self.env = env

    def _distance(self, target: np.ndarray) -> float:
        cur = self.env._get_curr_obs_combined_no_goal()  # the current frame, without touching the frame stack
        wh, wg, wo = self.weights
        return float(wh * np.linalg.norm(cur[0:3] - target[0:3]) + wg * abs(cur[3] - target[3])
                     + wo * np.linalg.norm(cur[4:7] - target[4:7]))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        if self.env is None:
            raise RuntimeError("MetaWorldShootingController: attach(env) before the first step")
        t, self.step = self.step, self.step + 1
        own = self.own[min(t, self.length - 1)]
        proposed = None if self.proposal is None else np.clip(self.proposal(obs), -1.0, 1.0)
        centre = own if proposed is None else proposed
        tries = [own] if proposed is None else [own, proposed]
        if self.candidates == 1:
            return centre
        extra = self.candidates - len(tries)  # >= 0: two fixed tries at most, and candidates >= 2 here
        tries = np.concatenate([np.stack(tries),
                                np.clip(centre + self.noise * self.rng.standard_normal((extra, 4)), -1.0, 1.0)])
        import mujoco

        u, last = self.env, self.length - 1

        def rollout(j: int, a: np.ndarray) -> float:
            dist = 0.0
            for k in range(max(1, min(self.lookahead, last - t))):
                b = a if k == 0 else np.clip(self.own[min(t + k, last)] + a - own, -1.0, 1.0)
                u.set_xyz_action(b[:3])
                u.do_simulation([b[-1], -b[-1]], n_frames=u.frame_skip)
                mujoco.mj_forward(u.model, u.data)
                dist += self._distance(self.path[min(t + 1 + k, last)])
            return dist

        return tries[shoot(u, tries, rollout, tolerance=self.tolerance)]
