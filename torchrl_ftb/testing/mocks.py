"""Mock environments for tests, in TorchRL's mock pattern (``torchrl/testing/mocking_classes.py``).

* :class:`ToyLineEnv` — a toy task whose reward, optimal behaviour and returns are known in
  closed form, so later stages can test that FTB *really* improves trajectories:
  a point moves in the plane, ``p' = p + dt * a``; the reward is
  ``r(s, a) = a_x - 0.5 * a_y**2`` (actions clipped to [-1, 1]); leaving the band
  ``|y| <= 1`` terminates the episode; reaching ``x >= success_x`` flags ``success``.
  The optimal policy is ``a = (1, 0)`` with return exactly ``max_steps``.
* :class:`MetaWorldMockEnv` — Meta-World-shaped (39-d observation, 4-d action in [-1, 1],
  ``success`` flag) with trivial hand-to-goal dynamics, for shape/plumbing tests.

Example:
    >>> from torchrl_ftb.testing import ToyLineEnv
    >>> env = ToyLineEnv(max_steps=8)
    >>> td = env.rollout(8)
    >>> td["next", "reward"].shape
    torch.Size([8, 1])
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = ["ToyLineEnv", "MetaWorldMockEnv", "toy_reward", "make_toy_dataset", "toy_optimal_return"]

TOY_OBS_DIM = 3  # (x, y, h / max_steps)
TOY_ACTION_DIM = 2
TOY_DT = 0.1


def toy_reward(observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Closed-form reward of the toy task, ``a_x - 0.5 a_y^2`` (actions clipped), shape ``[..., 1]``."""
    a = action.clamp(-1.0, 1.0)
    return (a[..., :1] - 0.5 * a[..., 1:2].pow(2)).to(torch.float32)


def toy_optimal_return(max_steps: int) -> float:
    """Return of the optimal toy policy ``a = (1, 0)``: one unit per step."""
    return float(max_steps)


def _bool_spec(device=None) -> Categorical:
    return Categorical(2, shape=(1,), dtype=torch.bool, device=device)


def _done_specs(shape=()) -> Composite:
    spec = Categorical(2, shape=(*shape, 1), dtype=torch.bool)
    return Composite(done=spec.clone(), terminated=spec.clone(), truncated=spec.clone(), shape=shape)


class ToyLineEnv(EnvBase):
    """Point in the plane with a closed-form reward (see module docstring).

    Args:
        max_steps: episode horizon (time limit → ``truncated``).
        success_x: x position counted as success (default ``0.6 * dt * max_steps``).
        device: torch device.
    """

    def __init__(self, *, max_steps: int = 32, success_x: float | None = None, device=None):
        super().__init__(device=device, batch_size=torch.Size([]))
        self.max_steps = int(max_steps)
        self.success_x = 0.6 * TOY_DT * max_steps if success_x is None else float(success_x)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(TOY_OBS_DIM,), dtype=torch.float32, device=self.device),
            success=_bool_spec(self.device),
            shape=(),
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(TOY_ACTION_DIM,), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32, device=self.device)
        self.done_spec = _done_specs()
        self._pos = torch.zeros(2)
        self._t = 0
        self._gen = torch.Generator().manual_seed(0)

    def _obs(self) -> torch.Tensor:
        return torch.tensor([*self._pos.tolist(), self._t / self.max_steps], dtype=torch.float32, device=self.device)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDict:
        self._pos = (torch.rand(2, generator=self._gen) - 0.5) * 0.2
        self._t = 0
        false = torch.zeros(1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {"observation": self._obs(), "done": false, "terminated": false.clone(), "truncated": false.clone(),
             "success": false.clone()},
            batch_size=[],
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        action = tensordict.get("action").detach().cpu().clamp(-1.0, 1.0)
        reward = toy_reward(self._obs().cpu(), action)
        self._pos = self._pos + TOY_DT * action
        self._t += 1
        terminated = bool(self._pos[1].abs() > 1.0)
        truncated = self._t >= self.max_steps and not terminated
        success = bool(self._pos[0] >= self.success_x)
        dev = self.device
        return TensorDict(
            {
                "observation": self._obs(),
                "reward": reward.to(dev),
                "done": torch.tensor([terminated or truncated], device=dev),
                "terminated": torch.tensor([terminated], device=dev),
                "truncated": torch.tensor([truncated], device=dev),
                "success": torch.tensor([success], device=dev),
            },
            batch_size=[],
            device=dev,
        )

    def _set_seed(self, seed: int | None) -> None:
        self._gen = torch.Generator().manual_seed(0 if seed is None else int(seed))


def make_toy_dataset(
    *,
    num_trajectories: int = 64,
    horizon: int = 32,
    seed: int = 0,
    quality: torch.Tensor | None = None,
    noise: float = 0.3,
) -> TensorDict:
    """A mixed-quality offline dataset of :class:`ToyLineEnv` episodes, ``[N, horizon]`` + mask.

    Each trajectory follows ``a = clip(q * (1, 0) + drift + noise)`` with a per-trajectory
    quality ``q`` (uniform in [-0.5, 1] unless given) and a sideways drift growing with
    ``1 - q``, so poor trajectories also tend to leave the band and terminate early
    (giving padded steps). The data obey exactly the env's dynamics and reward.

    Returns:
        Trajectory batch with ``observation``, ``action``, ``("next", ...)`` incl. ``reward``,
        ``done``, ``terminated``, ``truncated``, ``success``, and ``mask``; plus
        ``"quality"`` ``[N, H, 1]`` (the behaviour parameter, constant over time).
    """
    g = torch.Generator().manual_seed(seed)
    n, h = num_trajectories, horizon
    q = torch.rand(n, generator=g) * 1.5 - 0.5 if quality is None else quality.float().reshape(n)
    drift_sign = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0)
    drift = drift_sign * (1.0 - q).clamp(min=0.0) * 0.6
    eps = torch.randn(n, h, 2, generator=g) * noise
    action = torch.stack([q[:, None].expand(n, h), drift[:, None].expand(n, h)], -1) + eps
    action = action.clamp(-1.0, 1.0)
    pos0 = (torch.rand(n, 2, generator=g) - 0.5) * 0.2
    pos = pos0[:, None, :] + TOY_DT * torch.cumsum(action, 1)  # positions after each step
    prev = torch.cat([pos0[:, None, :], pos[:, :-1]], 1)
    t = torch.arange(h, dtype=torch.float32)
    obs = torch.cat([prev, (t / h).expand(n, h)[..., None]], -1)
    next_obs = torch.cat([pos, ((t + 1) / h).expand(n, h)[..., None]], -1)
    out_of_band = pos[..., 1].abs() > 1.0
    # first termination step (h if none)
    term_step = torch.where(out_of_band.any(1), out_of_band.float().argmax(1), torch.full((n,), h))
    steps = torch.arange(h)[None, :]
    mask = steps <= term_step[:, None].clamp(max=h - 1)
    mask = mask & (steps < h)
    terminated = (steps == term_step[:, None])
    truncated = (steps == h - 1) & ~terminated & mask
    success = (pos[..., 0] >= 0.6 * TOY_DT * h)
    reward = toy_reward(obs, action)
    m3 = mask[..., None]
    td = TensorDict(
        {
            "observation": obs * m3,
            "action": action * m3,
            "quality": q[:, None, None].expand(n, h, 1) * m3,
            "mask": mask,
            "next": {
                "observation": next_obs * m3,
                "reward": reward * m3,
                "done": ((terminated | truncated)[..., None]) & m3,
                "terminated": terminated[..., None] & m3,
                "truncated": truncated[..., None] & m3,
                "success": success[..., None] & m3,
            },
        },
        batch_size=[n, h],
    )
    return td


class MetaWorldMockEnv(EnvBase):
    """Meta-World-shaped mock: 39-d observation, 4-d action in [-1, 1], ``success`` flag.

    The hand (``obs[0:3]``) moves by ``0.05 * action[:3]``; the goal is ``obs[-3:]``;
    reward is ``-||hand - goal||``; success when the distance is below 0.05. Episodes are
    truncated after ``max_steps``. Used where a real Meta-World env is too slow for a unit test.
    """

    OBS_DIM = 39
    ACTION_DIM = 4

    def __init__(self, *, max_steps: int = 50, device=None):
        super().__init__(device=device, batch_size=torch.Size([]))
        self.max_steps = int(max_steps)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(self.OBS_DIM,), dtype=torch.float32, device=self.device),
            success=_bool_spec(self.device),
            shape=(),
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(self.ACTION_DIM,), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32, device=self.device)
        self.done_spec = _done_specs()
        self._gen = torch.Generator().manual_seed(0)
        self._obs = torch.zeros(self.OBS_DIM)
        self._t = 0

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        self._obs = torch.zeros(self.OBS_DIM)
        self._obs[0:3] = (torch.rand(3, generator=self._gen) - 0.5) * 0.2
        self._obs[3:36] = torch.randn(33, generator=self._gen) * 0.01
        self._obs[-3:] = (torch.rand(3, generator=self._gen) - 0.5) * 0.4
        self._t = 0
        false = torch.zeros(1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {"observation": self._obs.to(self.device), "done": false, "terminated": false.clone(),
             "truncated": false.clone(), "success": false.clone()},
            batch_size=[], device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        action = tensordict.get("action").detach().cpu().clamp(-1.0, 1.0)
        obs = self._obs.clone()
        obs[0:3] = obs[0:3] + 0.05 * action[:3]
        obs[3] = action[3]
        self._obs = obs
        self._t += 1
        dist = float((obs[0:3] - obs[-3:]).norm())
        dev = self.device
        truncated = self._t >= self.max_steps
        return TensorDict(
            {
                "observation": obs.to(dev),
                "reward": torch.tensor([-dist], dtype=torch.float32, device=dev),
                "done": torch.tensor([truncated], device=dev),
                "terminated": torch.zeros(1, dtype=torch.bool, device=dev),
                "truncated": torch.tensor([truncated], device=dev),
                "success": torch.tensor([dist < 0.05], device=dev),
            },
            batch_size=[], device=dev,
        )

    def _set_seed(self, seed: int | None) -> None:
        self._gen = torch.Generator().manual_seed(0 if seed is None else int(seed))

