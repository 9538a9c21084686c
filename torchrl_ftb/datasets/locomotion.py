"""MuJoCo locomotion datasets made locally, the way D4RL made its own (issue #7).

D4RL's ``medium-replay`` / ``medium`` / ``medium-expert`` datasets cannot be downloaded
here, so we rebuild them from our own SAC behaviour policies
(``recipes/train_behavior_policy.py``, gymnasium ``*-v5`` envs):

* ``medium``: rollouts of the *medium* policy — the first training checkpoint whose
  evaluation return reaches 1/3 of the best checkpoint's (D4RL: "≈1/3 of expert").
* ``medium-expert``: ``medium`` rollouts + rollouts of the *expert* (best) policy, equal parts.
* ``medium-replay``: the SAC replay buffer up to the frame where the medium checkpoint was
  saved (D4RL: "the replay buffer until the policy reaches medium performance").

Shipping without downloads: ``policies/<env>_{medium,expert}.pt`` are the actors (a few
hundred KB, ``torch.load(weights_only=True)``) and ``<env>_policies.json`` their record.
Decision for medium-replay: the replay buffer itself is shipped, *losslessly compacted*
(:func:`compact_replay`): MuJoCo is deterministic, so each episode is stored as its first
simulator state (float64) and its float32 actions, and :func:`resimulate_replay` replays
them to get back the exact observations, rewards and terminations (bit-exact on the
training machine; :func:`export_behavior_policies` verifies this and records the error).
That is ~4 bytes × action_dim per step instead of ~100 bytes. No re-collection with
intermediate checkpoints (an approximation) is needed.

Sizes are scaled to a CPU (``DEFAULT_NUM_TRANSITIONS``: 100k medium, 200k medium-expert;
D4RL ships 1M / 2M, see ``D4RL_NUM_TRANSITIONS``); medium-replay is whatever the CPU training
run collected before reaching "medium". Rollouts use the deterministic (mean) action by
default: our CPU-trained policies lose much more return when sampled (walker2d "expert"
694 deterministic vs 315 sampled, below the medium policy's 355), so sampled rollouts would
make the "expert" half of medium-expert worse than its medium half; ``deterministic=False``
samples instead. Time limits (and buffer cuts) are marked
``truncated``, never ``terminated``. Output follows ``docs/conventions.md`` with a
``"state"`` entry (float32 simulator ``qpos‖qvel``), is saved with
:func:`torchrl_ftb.data.save_trajectories` and cached by :func:`make_locomotion_dataset`
(registered as the ``"locomotion"`` generator, names ``<env>-<kind>``).

Example:
    >>> from torchrl_ftb.datasets.locomotion import load_behavior_policy, shipped_policy_path
    >>> policy, info = load_behavior_policy(shipped_policy_path("hopper", "medium"))
    >>> info["env_name"]
    'Hopper-v5'
    >>> td, meta = make_locomotion_dataset("hopper-medium-replay", progress=False)  # doctest: +SKIP
    >>> td["state"].shape[-1], meta["groups"]  # doctest: +SKIP
    (12, ['replay'])
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import InteractionType, NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Unbounded
from torchrl.envs import Transform, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal

from torchrl_ftb.data.trajectories import (
    atomic_torch_save,
    atomic_write_text,
    load_trajectories,
    pad_trajectories,
    save_trajectories,
    trajectories_to_flat,
)
from torchrl_ftb.datasets.registry import register_dataset_generator
from torchrl_ftb.envs import LOCOMOTION_ENVS, d4rl_normalized_score, locomotion_env_id, make_locomotion_env

__all__ = [
    "LOCOMOTION_KINDS",
    "DEFAULT_NUM_TRANSITIONS",
    "D4RL_NUM_TRANSITIONS",
    "POLICY_DIR",
    "SimulatorState",
    "make_behavior_env",
    "make_behavior_actor",
    "save_behavior_policy",
    "load_behavior_policy",
    "shipped_policy_path",
    "select_medium_checkpoint",
    "evaluate_policy",
    "collect_rollouts",
    "compact_replay",
    "resimulate_replay",
    "export_behavior_policies",
    "make_locomotion_dataset",
    "return_stats",
]

LOCOMOTION_KINDS: tuple[str, ...] = ("medium", "medium-replay", "medium-expert")
#: CPU-sized target transitions per dataset (medium-expert: half medium, half expert).
DEFAULT_NUM_TRANSITIONS: dict[str, int] = {"medium": 100_000, "medium-expert": 200_000}
#: D4RL v2 sizes, for the record (medium-replay: the whole buffer up to "medium").
D4RL_NUM_TRANSITIONS: dict[str, str] = {
    "medium": "1M",
    "medium-expert": "2M (1M medium + 1M expert)",
    "medium-replay": "hopper 402k, walker2d 302k, halfcheetah 202k",
}
POLICY_DIR = Path(__file__).resolve().parent / "policies"
MEDIUM_FRACTION = 1.0 / 3.0


# ----------------------------------------------------------------------------- envs
class SimulatorState(Transform):
    """Write the MuJoCo simulator state ``qpos‖qvel`` (float32) under ``out_key``.

    Locomotion observations drop the x position, so the full state is read from the
    wrapped gymnasium env (``env.base_env._env.unwrapped.data``) after every reset/step.
    Works on a single (non-batched) ``GymEnv``; hand-written because torchrl has no
    transform exposing simulator internals.

    Args:
        out_key: where to write the state.
        dtype: ``torch.float32`` (dataset convention) or ``torch.float64`` (exact, used by
            the training replay buffer so episodes can be re-simulated bit-for-bit).

    Example:
        >>> env = make_behavior_env("Hopper-v5", seed=0)  # doctest: +SKIP
        >>> env.rollout(3)["state"].shape  # doctest: +SKIP
        torch.Size([3, 12])
    """

    def __init__(self, *, out_key: str = "state", dtype: torch.dtype = torch.float32):
        super().__init__(in_keys=[], out_keys=[out_key])
        self.dtype = dtype

    def _data(self):
        parent = self.parent
        if parent is None:
            raise ValueError("SimulatorState: transform is not attached to an environment")
        gym_env = getattr(parent.base_env, "_env", None)
        if gym_env is None or not hasattr(gym_env.unwrapped, "data"):
            raise ValueError("SimulatorState: base env is not a single gymnasium MuJoCo env")
        return gym_env.unwrapped.data

    def _read(self, device) -> torch.Tensor:
        data = self._data()
        qpos = torch.as_tensor(data.qpos, dtype=self.dtype)
        qvel = torch.as_tensor(data.qvel, dtype=self.dtype)
        return torch.cat([qpos, qvel]).to(device)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set(self.out_keys[0], self._read(tensordict_reset.device))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.out_keys[0], self._read(next_tensordict.device))
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        data = self._data()
        dim = int(data.qpos.shape[0] + data.qvel.shape[0])
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*observation_spec.shape, dim), dtype=self.dtype, device=observation_spec.device
        )
        return observation_spec


def _short_name(env: str) -> str:
    env_id = locomotion_env_id(env)
    return next(k for k, v in LOCOMOTION_ENVS.items() if v == env_id)


def make_behavior_env(
    env: str, *, seed: int = 0, with_state: bool = True, state_dtype: torch.dtype = torch.float32,
    device: Any = "cpu",
) -> TransformedEnv:
    """Locomotion env for behaviour policies: ``make_locomotion_env`` (+ :class:`SimulatorState`).

    Args:
        env: short name (``"hopper"``) or gymnasium id (``"Hopper-v5"``).
        seed: env seed.
        with_state: append :class:`SimulatorState` (key ``"state"``).
        state_dtype: dtype of ``"state"``.
        device: torch device of the env outputs.

    Example:
        >>> env = make_behavior_env("hopper", seed=0)
        >>> td = env.rollout(3)
        >>> bool(torch.equal(td["observation"][:, :5], td["state"][:, 1:6]))  # obs = qpos[1:] || qvel
        True
    """
    base = make_locomotion_env(env, seed=seed, device=device)
    if with_state:
        base.append_transform(SimulatorState(dtype=state_dtype))
    return base


# ----------------------------------------------------------------------------- policies
def make_behavior_actor(
    *,
    obs_dim: int,
    action_dim: int,
    num_cells: Sequence[int] = (256, 256),
    action_low: float | Sequence[float] = -1.0,
    action_high: float | Sequence[float] = 1.0,
    device: Any = "cpu",
) -> ProbabilisticActor:
    """SAC Tanh-Normal actor (the torchrl ``sota-implementations/sac`` architecture).

    In: ``"observation"``; out: ``"action"`` (random in exploration mode, the tanh of the
    mean in deterministic mode), plus ``"loc"``/``"scale"``.

    Example:
        >>> actor = make_behavior_actor(obs_dim=11, action_dim=3, num_cells=(32, 32))
        >>> actor(TensorDict({"observation": torch.zeros(4, 11)}, [4]))["action"].shape
        torch.Size([4, 3])
    """
    net = nn.Sequential(
        MLP(in_features=obs_dim, out_features=2 * action_dim, num_cells=list(num_cells),
            activation_class=nn.ReLU, device=device),
        NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4),
    )
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    low = torch.as_tensor(action_low, dtype=torch.float32, device=device).expand(action_dim)
    high = torch.as_tensor(action_high, dtype=torch.float32, device=device).expand(action_dim)
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": low, "high": high, "tanh_loc": False},
        default_interaction_type=InteractionType.RANDOM,
        return_log_prob=False,
    )


def save_behavior_policy(
    actor: nn.Module, path: str | os.PathLike, *, config: dict, frames: int, eval_return: float,
    extra: dict | None = None,
) -> Path:
    """Save an actor checkpoint (weights + architecture + evaluation) atomically.

    The file holds only tensors and plain Python values so that
    ``torch.load(path, weights_only=True)`` reads it. ``config`` must contain the
    :func:`make_behavior_actor` arguments plus ``env_name``.
    """
    missing = {"env_name", "obs_dim", "action_dim", "num_cells"} - set(config)
    if missing:
        raise ValueError(f"save_behavior_policy: config is missing {sorted(missing)}")
    state = {k: v.detach().cpu().clone() for k, v in actor.state_dict().items()}
    payload = {
        "actor": state,
        "config": dict(config),
        "frames": int(frames),
        "eval_return": float(eval_return),
        **({"extra": extra} if extra else {}),
    }
    atomic_torch_save(payload, path)
    return Path(path)


def load_behavior_policy(path: str | os.PathLike, *, device: Any = "cpu") -> tuple[ProbabilisticActor, dict]:
    """Load a checkpoint written by :func:`save_behavior_policy` (``weights_only=True``).

    Returns:
        ``(actor, info)`` where ``info`` has ``env_name``, ``frames``, ``eval_return`` and the
        architecture config.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: the file is not a behaviour-policy checkpoint.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: behaviour-policy checkpoint not found")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or "actor" not in payload or "config" not in payload:
        raise ValueError(f"{path}: not a behaviour-policy checkpoint (needs 'actor' and 'config')")
    cfg = payload["config"]
    actor = make_behavior_actor(
        obs_dim=int(cfg["obs_dim"]), action_dim=int(cfg["action_dim"]), num_cells=cfg["num_cells"],
        action_low=cfg.get("action_low", -1.0), action_high=cfg.get("action_high", 1.0), device=device,
    )
    state = {k: v.float() if v.is_floating_point() else v for k, v in payload["actor"].items()}
    try:
        actor.load_state_dict(state)
    except RuntimeError as err:
        raise ValueError(f"{path}: actor weights do not match config {cfg}: {err}") from err
    info = {**cfg, "frames": payload.get("frames"), "eval_return": payload.get("eval_return"),
            "path": str(path), **payload.get("extra", {})}
    return actor, info


def shipped_policy_path(env: str, which: str) -> Path:
    """Path of a shipped policy, ``policies/<env>_<which>.pt`` (``which`` in medium/expert)."""
    if which not in ("medium", "expert"):
        raise ValueError(f"shipped_policy_path: which must be 'medium' or 'expert', got {which!r}")
    return POLICY_DIR / f"{_short_name(env)}_{which}.pt"


def select_medium_checkpoint(returns: Sequence[float], *, fraction: float = MEDIUM_FRACTION) -> tuple[int, int]:
    """Indices ``(medium, best)`` in a chronological list of checkpoint eval returns.

    ``best`` is the argmax; ``medium`` is the first checkpoint whose return reaches
    ``fraction`` of the best (D4RL: medium ≈ 1/3 of expert); with a negative best return
    (an untrained HalfCheetah) the threshold is the best return itself.

    Example:
        >>> select_medium_checkpoint([5.0, 40.0, 120.0, 300.0, 250.0])
        (2, 3)
    """
    if not len(returns):
        raise ValueError("select_medium_checkpoint: no checkpoint returns given")
    best = max(range(len(returns)), key=lambda i: returns[i])
    threshold = min(fraction * returns[best], returns[best])
    medium = next(i for i, r in enumerate(returns) if r >= threshold)
    return medium, best


# ----------------------------------------------------------------------------- rollouts
def _run_episodes(
    actor: nn.Module,
    env: str,
    *,
    num_episodes: int | None = None,
    num_transitions: int | None = None,
    num_envs: int = 16,
    seed: int = 0,
    deterministic: bool = False,
    max_episode_steps: int = 1000,
    progress: bool = False,
    desc: str = "rollouts",
) -> list[dict]:
    """Whole episodes of ``actor`` on ``num_envs`` gymnasium envs stepped side by side.

    Hand-written batched loop: torchrl's per-step overhead (~1 ms) dwarfs a MuJoCo step
    (~0.1 ms), so one batched policy call for ``num_envs`` envs is ~10x faster than
    ``env.rollout``. Observations/rewards get the float32 casts of ``make_locomotion_env``.
    Stops starting episodes once ``num_episodes`` are started or ``num_transitions`` are
    reached (counting running episodes), and lets the running ones finish.

    Returns:
        Episodes in start order, each a dict of numpy arrays (``observation`` [T+1, o],
        ``action`` [T, a], ``state`` [T, s] float64, ``reward`` [T], ``terminated`` [T]).
    """
    import gymnasium as gym
    from tqdm import tqdm

    if (num_episodes is None) == (num_transitions is None):
        raise ValueError("_run_episodes: give exactly one of num_episodes / num_transitions")
    env_id = locomotion_env_id(env)
    seeds = np.random.SeedSequence(seed)
    envs = [gym.make(env_id, max_episode_steps=max_episode_steps) for _ in range(num_envs)]
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    started, steps_done = 0, 0
    running: dict[int, dict] = {}
    finished: list[dict] = []
    bar = tqdm(total=num_transitions or num_episodes, desc=desc, disable=not progress)

    def want_more() -> bool:
        if num_episodes is not None:
            return started < num_episodes
        return steps_done + sum(len(ep["reward"]) for ep in running.values()) < num_transitions

    def start(k: int) -> None:
        nonlocal started
        obs, _ = envs[k].reset(seed=int(seeds.spawn(1)[0].generate_state(1)[0]))
        running[k] = {"index": started, "observation": [obs], "action": [], "state": [], "reward": [],
                      "terminated": []}
        started += 1

    for k in range(num_envs):
        if want_more():
            start(k)
    with torch.random.fork_rng(), torch.no_grad(), set_exploration_type(mode):
        torch.manual_seed(seed)
        while running:
            ks = sorted(running)
            obs = torch.as_tensor(np.stack([running[k]["observation"][-1] for k in ks]), dtype=torch.float32)
            action = actor(TensorDict({"observation": obs}, batch_size=[len(ks)])).get("action").numpy()
            for k, a in zip(ks, action):
                ep, sim = running[k], envs[k].unwrapped
                ep["state"].append(np.concatenate([sim.data.qpos, sim.data.qvel]))
                obs_k, reward, terminated, truncated, _ = envs[k].step(a.astype(np.float64))
                for key, value in (("observation", obs_k), ("action", a), ("reward", reward),
                                   ("terminated", terminated)):
                    ep[key].append(value)
                if terminated or truncated:
                    finished.append({key: np.asarray(v) for key, v in running.pop(k).items()})
                    steps_done += len(ep["reward"])
                    bar.update(len(ep["reward"]) if num_transitions is not None else 1)
                    if want_more():
                        start(k)
    bar.close()
    for e in envs:
        e.close()
    return sorted(finished, key=lambda ep: int(ep["index"]))


def _episode_tensordict(ep: dict) -> TensorDict:
    """One episode dict of :func:`_run_episodes` in the dataset layout (time limit = truncated)."""
    n = len(ep["reward"])
    f32 = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
    terminated = torch.as_tensor(np.asarray(ep["terminated"], dtype=bool)).unsqueeze(-1)
    truncated = torch.zeros_like(terminated)
    if not bool(terminated[-1]):
        truncated[-1] = True
    return TensorDict({
        "observation": f32(ep["observation"][:-1]),
        "action": f32(ep["action"]),
        "state": f32(ep["state"]),
        "next": {
            "observation": f32(ep["observation"][1:]),
            "reward": f32(ep["reward"]).unsqueeze(-1),
            "terminated": terminated,
            "truncated": truncated,
            "done": terminated | truncated,
        },
    }, batch_size=[n])


def evaluate_policy(actor: nn.Module, env: str, *, episodes: int = 10, deterministic: bool = True,
                    seed: int = 0, max_steps: int = 1000) -> list[float]:
    """Undiscounted returns of ``episodes`` episodes (deterministic = tanh of the mean action).

    Example:
        >>> actor = make_behavior_actor(obs_dim=11, action_dim=3, num_cells=(8,))
        >>> len(evaluate_policy(actor, "hopper", episodes=2, max_steps=5))
        2
    """
    eps = _run_episodes(actor, env, num_episodes=episodes, num_envs=episodes, seed=seed,
                        deterministic=deterministic, max_episode_steps=max_steps)
    return [float(np.asarray(ep["reward"], dtype=np.float32).sum()) for ep in eps]


def collect_rollouts(
    actor: nn.Module,
    env: str,
    *,
    num_transitions: int,
    seed: int = 0,
    deterministic: bool = False,
    max_episode_steps: int = 1000,
    num_envs: int = 16,
    progress: bool = True,
    desc: str = "rollouts",
) -> TensorDict:
    """Whole episodes of ``actor`` until at least ``num_transitions`` steps are collected.

    Args:
        actor: a policy module reading ``"observation"``, writing ``"action"`` (e.g.
            :func:`load_behavior_policy`).
        env: locomotion env name.
        num_transitions: minimum number of steps (episodes are kept whole).
        seed: env-reset and action-sampling seed (the global torch RNG is not disturbed).
        deterministic: act with the mean action instead of sampling (D4RL sampled).
        max_episode_steps: time limit (the env's own is 1000); reaching it is ``truncated``.
        num_envs: envs stepped side by side (results depend on it: it sets the RNG order).
        progress: tqdm bar.

    Returns:
        ``[N, H]`` trajectory batch (``docs/conventions.md`` keys + float32 ``"state"``).

    Example:
        >>> actor = make_behavior_actor(obs_dim=11, action_dim=3, num_cells=(8,))
        >>> td = collect_rollouts(actor, "hopper", num_transitions=20, max_episode_steps=10, progress=False)
        >>> bool(td["mask"].sum() >= 20)
        True
    """
    if num_transitions < 1:
        raise ValueError(f"collect_rollouts: num_transitions must be >= 1, got {num_transitions}")
    eps = _run_episodes(actor, env, num_transitions=num_transitions, num_envs=num_envs, seed=seed,
                        deterministic=deterministic, max_episode_steps=max_episode_steps,
                        progress=progress, desc=desc)
    return pad_trajectories([_episode_tensordict(ep) for ep in eps])


# ----------------------------------------------------------------------------- replay buffer
COMPACT_REPLAY_FORMAT = "torchrl_ftb.compact_replay/1"


def compact_replay(storage: TensorDictBase, *, env: str, num_frames: int) -> dict:
    """Compress the first ``num_frames`` transitions of a training replay buffer, losslessly.

    MuJoCo is deterministic, so an episode is fully described by its first simulator state
    (float64) and its actions: the compact form stores just those (≈ action size per step)
    plus per-episode returns to verify re-simulation (:func:`resimulate_replay`).

    Args:
        storage: flat ``[T]`` buffer in collection order with ``"action"``, float64
            ``"state"``, ``("collector", "traj_ids")`` and ``("next", "reward"/"done")``.
        env: locomotion env name.
        num_frames: prefix length to keep (e.g. the frame count of the medium checkpoint).

    Returns:
        A dict of tensors/plain values (``torch.save``-able, ``weights_only`` loadable).
    """
    keys = set(storage.keys(True))
    for key in ("action", "state", ("collector", "traj_ids"), ("next", "reward"), ("next", "done")):
        if key not in keys:
            raise ValueError(f"compact_replay: replay storage has no {key!r} entry")
    if num_frames < 1 or num_frames > storage.shape[0]:
        raise ValueError(f"compact_replay: num_frames={num_frames} outside [1, {storage.shape[0]}]")
    state = storage.get("state")[:num_frames]
    if state.dtype != torch.float64:
        raise ValueError("compact_replay: 'state' must be float64 (train with state_dtype=torch.float64) "
                         f"for exact re-simulation, got {state.dtype}")
    traj = storage.get(("collector", "traj_ids"))[:num_frames]
    new = torch.ones(num_frames, dtype=torch.bool)
    new[1:] = traj[1:] != traj[:-1]
    starts = new.nonzero().squeeze(-1)
    lengths = torch.diff(torch.cat([starts, torch.tensor([num_frames])]))
    ends = starts + lengths - 1
    reward = storage.get(("next", "reward"))[:num_frames].squeeze(-1).double()
    episode = torch.repeat_interleave(torch.arange(len(starts)), lengths)
    returns = torch.zeros(len(starts), dtype=torch.float64).index_add_(0, episode, reward)
    done = storage.get(("next", "done"))[:num_frames].squeeze(-1)
    if bool(done[:-1][~new[1:]].any()):
        raise ValueError("compact_replay: an episode continues after 'done' (trajectory ids broken)")
    return {
        "format": COMPACT_REPLAY_FORMAT,
        "env_id": locomotion_env_id(env),
        "num_frames": int(num_frames),
        "init_state": state[starts].clone(),
        "actions": storage.get("action")[:num_frames].to(torch.float32).clone(),
        "lengths": lengths.to(torch.int64),
        "returns": returns.to(torch.float32),
        "ended": done[ends].clone(),  # False: cut at num_frames (-> truncated)
    }


def resimulate_replay(compact: dict, *, max_episodes: int | None = None,
                      progress: bool = True) -> tuple[TensorDict, dict]:
    """Rebuild the trajectories of a :func:`compact_replay` by replaying its actions.

    Steps the gymnasium env directly (a torchrl env cannot be reset to a given simulator
    state), with the same float32 casts as ``make_locomotion_env``. Episodes are exact
    (same MuJoCo build); a cut last episode ends with ``truncated``.

    Args:
        compact: the dict of :func:`compact_replay` (e.g. ``torch.load`` of a shipped
            ``<env>_medium_replay.pt`` with ``weights_only=True``).
        max_episodes: only the first episodes (for quick checks).
        progress: tqdm bar.

    Returns:
        ``(td, check)``: the ``[E, H]`` trajectory batch and ``{"max_return_error",
        "early_terminations"}`` against the recorded returns (0 and 0 when exact).
    """
    import gymnasium as gym
    import mujoco
    from tqdm import tqdm

    if compact.get("format") != COMPACT_REPLAY_FORMAT:
        raise ValueError(f"resimulate_replay: unknown format {compact.get('format')!r} "
                         f"(expected {COMPACT_REPLAY_FORMAT!r})")
    gym_env = gym.make(compact["env_id"])
    gym_env.reset(seed=0)
    sim = gym_env.unwrapped
    nq = sim.model.nq
    actions = compact["actions"].numpy()
    lengths = compact["lengths"].tolist()[:max_episodes]
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    episodes, max_err, early = [], 0.0, 0
    for e in tqdm(range(len(lengths)), desc=f"re-simulate {compact['env_id']}", disable=not progress):
        init = compact["init_state"][e].numpy()
        # as a reset does: a fresh mjData (the previous episode's solver warm start would otherwise
        # carry over and, with HalfCheetah's many contacts, change the trajectory)
        mujoco.mj_resetData(sim.model, sim.data)
        sim.set_state(init[:nq], init[nq:])
        n = lengths[e]
        obs = np.empty((n + 1, sim.observation_space.shape[0]))
        state = np.empty((n, init.shape[0]))
        reward = np.empty(n)
        terminated = np.zeros(n, dtype=bool)
        obs[0] = sim._get_obs()
        for t in range(n):
            state[t] = np.concatenate([sim.data.qpos, sim.data.qvel])
            obs[t + 1], reward[t], terminated[t], _, _ = sim.step(actions[offsets[e] + t].astype(np.float64))
            if terminated[t] and t < n - 1:
                early += 1
        truncated = np.zeros(n, dtype=bool)
        if not terminated[-1]:
            truncated[-1] = True
        max_err = max(max_err, abs(float(reward.astype(np.float32).astype(np.float64).sum())
                                   - float(compact["returns"][e])))
        f32 = lambda x: torch.as_tensor(x, dtype=torch.float32)  # noqa: E731
        td = TensorDict({
            "observation": f32(obs[:-1]),
            "action": torch.as_tensor(actions[offsets[e]:offsets[e + 1]]),
            "state": f32(state),
            "next": {
                "observation": f32(obs[1:]),
                "reward": f32(reward).unsqueeze(-1),
                "terminated": torch.as_tensor(terminated).unsqueeze(-1),
                "truncated": torch.as_tensor(truncated).unsqueeze(-1),
                "done": torch.as_tensor(terminated | truncated).unsqueeze(-1),
            },
        }, batch_size=[n])
        episodes.append(td)
    gym_env.close()
    return pad_trajectories(episodes), {"max_return_error": max_err, "early_terminations": early}


# ----------------------------------------------------------------------------- shipping
def _git_commit() -> str | None:
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).resolve().parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def export_behavior_policies(
    run_dir: str | os.PathLike,
    *,
    out_dir: str | os.PathLike = POLICY_DIR,
    eval_episodes: int = 10,
    seed: int = 123,
    progress: bool = True,
) -> dict:
    """Pick and ship the medium/expert policies and the medium-replay buffer of a SAC run.

    Reads ``progress.json`` of ``recipes/train_behavior_policy.py``, selects the checkpoints
    with :func:`select_medium_checkpoint` (by their training-time evaluation), re-evaluates
    both on ``eval_episodes`` fresh episodes, and writes to ``out_dir``:
    ``<env>_medium.pt``, ``<env>_expert.pt`` (float32 actors), ``<env>_medium_replay.pt``
    (:func:`compact_replay` of the buffer up to the medium checkpoint, verified by
    :func:`resimulate_replay`) and ``<env>_policies.json`` (the record).

    Returns:
        The JSON record as a dict.
    """
    run_dir = Path(run_dir)
    out_dir = Path(out_dir)
    progress_file = run_dir / "progress.json"
    if not progress_file.exists():
        raise FileNotFoundError(f"{progress_file}: not a train_behavior_policy run (no progress.json)")
    record = json.loads(progress_file.read_text())
    ckpts = record.get("checkpoints") or []
    if not ckpts:
        raise ValueError(f"{progress_file}: the run saved no checkpoints")
    env_id = record["arch"]["env_name"]
    short = _short_name(env_id)
    medium_i, best_i = select_medium_checkpoint([c["eval_return"] for c in ckpts])
    shipped = {}
    for which, idx in (("medium", medium_i), ("expert", best_i)):
        actor, info = load_behavior_policy(run_dir / ckpts[idx]["path"])
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            rets = evaluate_policy(actor, env_id, episodes=eval_episodes, seed=seed)
            rets_stoch = evaluate_policy(actor, env_id, episodes=eval_episodes, seed=seed, deterministic=False)
        dest = out_dir / f"{short}_{which}.pt"
        reeval = {"eval_returns_deterministic": rets, "eval_returns_stochastic": rets_stoch}
        save_behavior_policy(actor, dest, config={k: info[k] for k in
                                                  ("env_name", "obs_dim", "action_dim", "num_cells",
                                                   "action_low", "action_high")},
                             frames=info["frames"], eval_return=info["eval_return"],
                             extra={"which": which, **reeval})
        mean_det = sum(rets) / len(rets)
        shipped[which] = {
            "file": dest.name, "bytes": dest.stat().st_size, "frames": info["frames"],
            "train_eval_return": info["eval_return"], **reeval,
            "mean_return_deterministic": mean_det,
            "mean_return_stochastic": sum(rets_stoch) / len(rets_stoch),
            "d4rl_normalized_score_approx": float(d4rl_normalized_score(short, mean_det)),
        }
    # medium-replay: the buffer up to the medium checkpoint, compact + verified
    storage_dir = run_dir / "replay_buffer" / "storage"
    if not storage_dir.exists():  # run stopped before its final dump: the live memmap scratch
        storage_dir = run_dir / "replay_scratch"
    storage = TensorDict.load_memmap(storage_dir)
    frames = int(ckpts[medium_i]["frames"])
    compact = compact_replay(storage, env=env_id, num_frames=frames)
    replay_file = out_dir / f"{short}_medium_replay.pt"
    atomic_torch_save(compact, replay_file)
    resim, check = resimulate_replay(compact, progress=progress)
    flat_obs = storage.get("observation")[:frames]
    flat = trajectories_to_flat(resim)
    check["max_observation_error"] = float((flat.get("observation") - flat_obs).abs().max())
    check["max_reward_error"] = float(
        (flat.get(("next", "reward")) - storage.get(("next", "reward"))[:frames]).abs().max())
    returns = (resim.get(("next", "reward")).squeeze(-1) * resim.get("mask")).sum(-1)
    out = {
        "env_id": env_id,
        "command": record.get("command"),
        "training_config": record.get("config"),
        "training_commit": record.get("commit"),
        "export_commit": _git_commit(),
        "machine": record.get("machine"),
        "seed": record.get("config", {}).get("seed"),
        "training_frames": record.get("frames"),
        "training_updates": record.get("updates"),
        "training_wall_s": record.get("wall_s"),
        "training_steps_per_s": record.get("steps_per_s"),
        "stop_reason": record.get("stop_reason"),
        "selection": "expert = best training eval return (mean of the run's eval episodes, deterministic); "
                     "medium = first checkpoint reaching 1/3 of it (D4RL: medium ~ 1/3 expert)",
        "checkpoints": [{"frames": c["frames"], "eval_return": c["eval_return"]} for c in ckpts],
        "policies": shipped,
        "medium_replay": {
            "file": replay_file.name, "bytes": replay_file.stat().st_size, "frames": frames,
            "episodes": int(resim.shape[0]),
            "return_min": float(returns.min()), "return_median": float(returns.median()),
            "return_max": float(returns.max()), "resimulation_check": check,
        },
        "d4rl_score_note": "approximate: gymnasium v5 envs vs D4RL's v2 (mujoco-py) reference returns",
    }
    atomic_write_text(out_dir / f"{short}_policies.json", json.dumps(out, indent=2))
    return out


# ----------------------------------------------------------------------------- datasets
def _parse_name(name: str) -> tuple[str, str]:
    base = name[:-3] if name.endswith("-v2") else name
    for kind in sorted(LOCOMOTION_KINDS, key=len, reverse=True):
        if base.endswith("-" + kind):
            env = base[: -len(kind) - 1]
            if env in LOCOMOTION_ENVS:
                return env, kind
    raise ValueError(f"unknown locomotion dataset {name!r}; expected '<env>-<kind>' with env in "
                     f"{sorted(LOCOMOTION_ENVS)} and kind in {list(LOCOMOTION_KINDS)}")


def return_stats(td: TensorDictBase, *, env: str | None = None) -> dict:
    """Episodes, transitions, mean length and undiscounted return min/median/mean/max
    (+ approximate D4RL normalized scores when ``env`` is given).

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> return_stats(make_toy_dataset(num_trajectories=3, horizon=5))["episodes"]
        3
    """
    mask = td.get("mask")
    ret = (td.get(("next", "reward")).squeeze(-1) * mask).sum(-1)
    out = {
        "episodes": int(mask.shape[0]), "transitions": int(mask.sum()),
        "mean_length": float(mask.sum(-1).float().mean()),
        "return_min": float(ret.min()), "return_median": float(ret.median()),
        "return_mean": float(ret.mean()), "return_max": float(ret.max()),
    }
    if env is not None:
        for k in ("min", "median", "mean", "max"):
            out[f"d4rl_score_{k}_approx"] = float(d4rl_normalized_score(env, out[f"return_{k}"]))
    return out


def _dataset_config(env: str, kind: str, num_transitions: int | None, seed: int, deterministic: bool,
                    policy_dir: Path) -> dict:
    import hashlib
    import importlib.metadata

    files = {"medium": ["medium"], "medium-expert": ["medium", "expert"], "medium-replay": ["medium_replay"]}[kind]
    digests = {f: hashlib.sha1((policy_dir / f"{env}_{f}.pt").read_bytes()).hexdigest()[:12]
               for f in files if (policy_dir / f"{env}_{f}.pt").exists()}
    return {
        "env": env, "env_id": LOCOMOTION_ENVS[env], "kind": kind,
        "num_transitions": None if kind == "medium-replay" else int(num_transitions),
        "seed": int(seed), "deterministic": bool(deterministic), "policy_files": digests,
        "generator": "torchrl_ftb.datasets.locomotion", "generator_version": 1,
        # the rollouts are the simulator's: another MuJoCo or gymnasium build is another dataset (as Meta-World's key)
        "mujoco_version": importlib.metadata.version("mujoco"),
        "gymnasium_version": importlib.metadata.version("gymnasium"),
    }


def make_locomotion_dataset(
    name: str,
    *,
    num_transitions: int | None = None,
    seed: int = 0,
    deterministic: bool = True,
    policy_dir: str | os.PathLike = POLICY_DIR,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
) -> tuple[TensorDict, dict]:
    """Build (or load from the cache) a D4RL-style locomotion dataset from shipped policies.

    Args:
        name: ``"<env>-<kind>"``, env in hopper/walker2d/halfcheetah, kind in
            ``medium``/``medium-replay``/``medium-expert`` (a trailing ``-v2`` is accepted).
        num_transitions: total size (medium-expert: half from each policy; default
            :data:`DEFAULT_NUM_TRANSITIONS`; ignored for medium-replay, whose size is fixed by
            the training run). Whole episodes are kept, so sizes are "at least".
        seed: rollout seed (env resets and action sampling).
        deterministic: act with the mean action (default; see the module docstring),
            else sample from the policy.
        policy_dir: folder with ``<env>_{medium,expert}.pt`` / ``<env>_medium_replay.pt``.
        cache_dir: cache root (default ``$TORCHRL_FTB_DATA`` or ``~/.cache/torchrl_ftb/datasets``).
        progress: tqdm bars.

    Returns:
        ``(td, meta)``: the ``[N, H]`` trajectory batch (with ``"state"``) and the metadata of
        ``meta.json`` plus ``meta["path"]`` and ``meta["per_trajectory"]`` (``[N]``
        TensorDict with ``"group"``, an index into ``meta["groups"]``).

    Raises:
        ValueError: bad name or option. FileNotFoundError: shipped policy files missing.
    """
    import hashlib
    import platform
    import time

    from torchrl_ftb.datasets.metaworld import default_cache_dir

    env, kind = _parse_name(name)
    policy_dir = Path(policy_dir)
    if num_transitions is None and kind != "medium-replay":
        num_transitions = DEFAULT_NUM_TRANSITIONS[kind]
    if num_transitions is not None and num_transitions < 2:
        raise ValueError(f"{name}: num_transitions must be >= 2, got {num_transitions}")
    config = _dataset_config(env, kind, num_transitions, seed, deterministic, policy_dir)
    digest = hashlib.sha1(json.dumps(config, sort_keys=True).encode()).hexdigest()[:12]
    root = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
    path = root / f"{env}-{kind}-seed{seed}-{digest}"
    if (path / "meta.json").exists():
        td, meta, per = load_trajectories(path, with_per_trajectory=True)
        return td, {**meta, "path": str(path), "per_trajectory": per}

    start = time.perf_counter()
    policies, extra_meta = {}, {}
    if kind == "medium-replay":
        replay_file = policy_dir / f"{env}_medium_replay.pt"
        if not replay_file.exists():
            raise FileNotFoundError(f"{replay_file}: shipped medium-replay buffer not found")
        compact = torch.load(replay_file, map_location="cpu", weights_only=True)
        td, check = resimulate_replay(compact, progress=progress)
        groups = ["replay"]
        per = TensorDict({"group": torch.zeros(td.shape[0], dtype=torch.int64)}, batch_size=td.shape[:1])
        extra_meta = {"resimulation_check": check, "replay_frames": int(compact["num_frames"])}
    else:
        parts = ["medium"] if kind == "medium" else ["medium", "expert"]
        chunks = []
        for i, which in enumerate(parts):
            actor, info = load_behavior_policy(policy_dir / f"{env}_{which}.pt")
            policies[which] = {"frames": info.get("frames"), "train_eval_return": info.get("eval_return"),
                               "eval_returns_deterministic": info.get("eval_returns_deterministic"),
                               "eval_returns_stochastic": info.get("eval_returns_stochastic")}
            n = num_transitions // len(parts)
            chunks.append(collect_rollouts(actor, env, num_transitions=n, seed=seed + 1000 * i,
                                           deterministic=deterministic, progress=progress,
                                           desc=f"{env}-{kind} ({which})"))
        groups = parts
        horizon = max(c.shape[1] for c in chunks)
        chunks = [c if c.shape[1] == horizon else _pad_to(c, horizon) for c in chunks]
        td = torch.cat(chunks, 0)
        per = TensorDict({"group": torch.cat([torch.full((c.shape[0],), i, dtype=torch.int64)
                                              for i, c in enumerate(chunks)])}, batch_size=td.shape[:1])
    meta = {
        "env_id": LOCOMOTION_ENVS[env], "domain": "locomotion", "name": f"{env}-{kind}", **config,
        "groups": groups, "policies": policies, **extra_meta,
        "state_dim": int(td.get("state").shape[-1]),
        "stats": return_stats(td, env=env),
        "d4rl_size": D4RL_NUM_TRANSITIONS[kind],
        "truncation": "time limit (1000 steps) and buffer cuts are ('next','truncated'), never terminated",
        "generation_seconds": round(time.perf_counter() - start, 2),
        "machine": platform.platform(),
    }
    save_trajectories(td, path, meta=meta, per_trajectory=per)
    td, meta, per = load_trajectories(path, with_per_trajectory=True)
    return td, {**meta, "path": str(path), "per_trajectory": per}


def _pad_to(td: TensorDict, horizon: int) -> TensorDict:
    """Zero-pad an ``[N, H]`` batch to ``[N, horizon]`` (mask False on the new steps)."""
    pad = td[:, :1].expand(td.shape[0], horizon - td.shape[1]).clone().zero_()
    return torch.cat([td, pad], 1)


def _is_locomotion_dataset(name: str) -> bool:
    try:
        _parse_name(name)
    except ValueError:
        return False
    return True


def _generate_for_registry(env: str, *, seed: int = 0, num_transitions: int | None = None,
                           deterministic: bool = True, out: str | None = None,
                           progress: bool = True) -> tuple[TensorDict, dict]:
    return make_locomotion_dataset(env, num_transitions=num_transitions, seed=seed, deterministic=deterministic,
                                   cache_dir=out, progress=progress)


register_dataset_generator(
    "locomotion",
    _generate_for_registry,
    matches=_is_locomotion_dataset,
    description="hopper|walker2d|halfcheetah-{medium,medium-replay,medium-expert}: D4RL recipe from our "
                "own shipped SAC policies (gymnasium v5)",
)
