"""Offline Meta-World datasets with IPL's recipe (the data FTB's Meta-World results use).

Per task, four groups of ``episodes_per_group`` episodes (default 100 each):

0. ``expert``: the task's scripted policy, one fixed goal (the env's goal for ``seed``),
   Gaussian action noise ``N(0, noise^2)``;
1. ``within``: the same policy with a new random goal at every reset, same noise;
2. ``random``: uniform random actions;
3. ``cross``: the scripted policy of a *different* task (drawn per episode) acting in this
   task's env (random goals), same noise.

Actions are clipped to ``(-1 + 1e-5, 1 - 1e-5)`` after the noise. An episode stops after
25 consecutive success steps (``truncated``, not ``terminated``) or at ``max_steps``.
Each step keeps the simulator ``state`` = qpos‖qvel of ``s_h``. Every episode draws its
randomness from ``SeedSequence([seed, group, episode])``, so the data are identical for a
seed whatever the number of worker processes.

Example:
    >>> from torchrl_ftb.datasets import make_metaworld_dataset, dataset_stats
    >>> td, meta = make_metaworld_dataset("button-press-v3", episodes_per_group=1,
    ...                                   max_steps=20, progress=False)  # doctest: +SKIP
    >>> td.batch_size, meta["groups"]  # doctest: +SKIP
    (torch.Size([4, 20]), ['expert', 'within', 'random', 'cross'])
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from torchrl_ftb.data import load_trajectories, save_trajectories
from torchrl_ftb.datasets.registry import register_dataset_generator
from torchrl_ftb.envs.metaworld import (
    METAWORLD_MAX_EPISODE_STEPS,
    check_metaworld_task,
    configure_goal,
    make_metaworld_gym_env,
    metaworld_tasks,
    scripted_policy,
)

__all__ = [
    "GROUPS",
    "GENERATOR_VERSION",
    "SUCCESS_STREAK",
    "ACTION_CLIP",
    "default_cache_dir",
    "make_metaworld_dataset",
    "generate_metaworld_episodes",
    "replay_metaworld_actions",
    "check_groups",
    "dataset_stats",
    "format_stats",
]

GROUPS = ("expert", "within", "random", "cross")
GENERATOR_VERSION = 2  # 2: scripted policies read a copy of the observation (v1 recorded door
#                        policies' in-place shifts of the object position in cross-env episodes)
SUCCESS_STREAK = 25  # stop after this many consecutive success steps
ACTION_CLIP = 1.0 - 1e-5


def default_cache_dir() -> Path:
    """``$TORCHRL_FTB_DATA`` if set, else ``~/.cache/torchrl_ftb/datasets``."""
    env = os.environ.get("TORCHRL_FTB_DATA")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "torchrl_ftb" / "datasets"


def _episode_rng(seed: int, group: int, episode: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, group, episode]))


def _run_episode(env, task: str, group: int, rng: np.random.Generator, *, noise: float,
                 max_steps: int, policies: dict, expert: bool = False, actions: np.ndarray | None = None,
                 controller=None) -> dict:
    """One episode of ``group`` (see module docstring); returns numpy arrays per step.

    ``expert=True`` replays the episode's goal and start with the task's own scripted policy
    instead of the group's (``bench/expert_headroom.py``: what the expert reaches from there).
    ``actions [L, 4]``: the episode's goal and start, then these actions open loop (clipped as the
    data's), stopping after ``L`` steps or at the stop rule, whichever comes first. ``controller``
    (``obs -> action``, called once per step in order): the episode's goal and start, then this
    closed-loop controller instead of the group's policy; one with an ``attach`` method gets the unwrapped env
    first (:class:`~torchrl_ftb.envs.MetaWorldShootingController`)."""
    name = GROUPS[group]
    tasks = metaworld_tasks()
    policy_task = -1
    if name in ("expert", "within"):
        policy_task = tasks.index(task)
    elif name == "cross":
        others = [i for i, t in enumerate(tasks) if t != task]
        policy_task = int(others[rng.integers(len(others))])
    # expert: the fixed goal of `seed`; others: a goal drawn from this episode's generator
    configure_goal(env, random_goal=name != "expert", seed=int(rng.integers(2**63)))
    if expert:  # after the group's draws, so the goal and start are the episode's own
        policy_task = tasks.index(task)
    u = env.unwrapped
    policy = controller
    if controller is not None and hasattr(controller, "attach"):  # a controller that shoots in the simulator
        controller.attach(u)
    if policy is None and policy_task >= 0:  # a given controller needs no scripted policy built
        if tasks[policy_task] not in policies:
            policies[tasks[policy_task]] = scripted_policy(tasks[policy_task])
        policy = policies[tasks[policy_task]]

    obs, _ = u.reset()
    steps = {k: [] for k in ("observation", "action", "next_observation", "reward", "success", "state")}
    streak = 0
    for t in range(max_steps if actions is None else min(max_steps, len(actions))):
        state = np.concatenate([u.data.qpos, u.data.qvel])
        if actions is not None:
            action = np.asarray(actions[t], dtype=np.float64)
        elif policy is None:
            action = rng.uniform(-1.0, 1.0, size=4)
        else:
            action = policy(obs) + noise * rng.standard_normal(4)
        action = np.clip(action, -ACTION_CLIP, ACTION_CLIP)
        next_obs, reward, _, _, info = u.step(action)
        success = bool(info["success"])
        streak = streak + 1 if success else 0
        for key, value in (("observation", obs), ("action", action), ("next_observation", next_obs),
                           ("reward", reward), ("success", success), ("state", state)):
            steps[key].append(value)
        if streak >= SUCCESS_STREAK:
            break
        obs = next_obs
    out = {k: np.asarray(v) for k, v in steps.items()}
    out["group"], out["policy_task"] = group, policy_task
    return out


def generate_metaworld_episodes(task: str, jobs: list[tuple[int, int]], *, seed: int, noise: float,
                                max_steps: int, on_episode=None, expert: bool = False,
                                actions: "list[np.ndarray] | None" = None, controllers: list | None = None) -> list[dict]:
    """Generate the episodes ``jobs = [(group, episode), ...]`` (a worker's share).

    Deterministic per ``(seed, group, episode)``; used in-process or in worker processes.
    ``on_episode()`` (optional) is called after each episode (progress bar). ``expert=True``:
    every episode's goal and start as generated, acted on by the task's scripted policy
    (with ``noise``) whatever its group. ``actions`` (one ``[L_i, 4]`` array per job): an
    open-loop replay, each episode's goal and start acted on by those actions instead
    (:func:`replay_metaworld_actions`). ``controllers`` (one ``obs -> action`` callable per job): each
    episode's goal and start, then that controller in closed loop (:func:`torchrl_ftb.analysis.track_paths`).
    """
    if controllers is not None and len(controllers) != len(jobs):
        raise ValueError(f"generate_metaworld_episodes: {len(controllers)} controllers for {len(jobs)} jobs")
    if actions is not None and len(actions) != len(jobs):
        raise ValueError(f"generate_metaworld_episodes: {len(actions)} action sequences for {len(jobs)} jobs")
    env = make_metaworld_gym_env(task, seed=seed, max_episode_steps=max_steps)
    policies: dict = {}
    out = []
    for i, (group, episode) in enumerate(jobs):
        ep = _run_episode(env, task, group, _episode_rng(seed, group, episode), noise=noise,
                          max_steps=max_steps, policies=policies, expert=expert,
                          actions=None if actions is None else actions[i],
                          controller=None if controllers is None else controllers[i])
        ep["episode"] = episode
        out.append(ep)
        if on_episode is not None:
            on_episode()
    return out


def replay_metaworld_actions(task: str, jobs: list[tuple[int, int]], actions: "list[np.ndarray]", *, seed: int,
                             max_steps: int = METAWORLD_MAX_EPISODE_STEPS, on_episode=None) -> list[dict]:
    """Open-loop replay: each dataset episode's own goal and start, then a given action sequence.

    The simulator's answer to "what do these actions do from there?": for a generated trajectory,
    replay its actions from the start of the dataset episode it was made from and compare the
    simulator's rewards with the ones read off the generated states. Actions are clipped as the
    data's; an episode stops after its actions or at the data's stop rule (``SUCCESS_STREAK``
    consecutive successes). Replaying a recorded episode's own actions reproduces it.

    Args:
        task: Meta-World v3 task name.
        jobs: ``(group index, episode)`` per sequence (a dataset's ``meta["per_trajectory"]``;
            the group index into :data:`GROUPS`).
        actions: one ``[L_i, 4]`` array per job.
        seed: the dataset's generator seed (``meta["seed"]``).
        max_steps: the time limit.
        on_episode: called after each episode (progress bar).

    Returns:
        One dict of per-step numpy arrays per job (``observation``, ``action``, ``reward``,
        ``success``, ...), as :func:`generate_metaworld_episodes`.

    Example:
        >>> import numpy as np
        >>> eps = replay_metaworld_actions("button-press-v3", [(0, 0)], [np.zeros((5, 4))],
        ...                                seed=0)  # doctest: +SKIP
        >>> eps[0]["reward"].shape  # doctest: +SKIP
        (5,)
    """
    check_metaworld_task(task)
    seqs = [np.clip(np.asarray(a, dtype=np.float64), -ACTION_CLIP, ACTION_CLIP) for a in actions]
    for i, a in enumerate(seqs):
        if a.ndim != 2 or a.shape[-1] != 4:
            raise ValueError(f"replay_metaworld_actions: actions[{i}] has shape {list(a.shape)}, expected [L, 4]")
    return generate_metaworld_episodes(task, jobs, seed=seed, noise=0.0, max_steps=max_steps,
                                       on_episode=on_episode, actions=seqs)


def _to_trajectories(episodes: list[dict], horizon: int) -> tuple[TensorDict, TensorDict]:
    n = len(episodes)
    obs_dim = episodes[0]["observation"].shape[-1]
    state_dim = episodes[0]["state"].shape[-1]
    obs = torch.zeros(n, horizon, obs_dim)
    nxt = torch.zeros(n, horizon, obs_dim)
    act = torch.zeros(n, horizon, 4)
    rew = torch.zeros(n, horizon, 1)
    succ = torch.zeros(n, horizon, 1, dtype=torch.bool)
    state = torch.zeros(n, horizon, state_dim)
    mask = torch.zeros(n, horizon, dtype=torch.bool)
    for i, ep in enumerate(episodes):
        t = len(ep["reward"])
        obs[i, :t] = torch.as_tensor(ep["observation"], dtype=torch.float32)
        nxt[i, :t] = torch.as_tensor(ep["next_observation"], dtype=torch.float32)
        act[i, :t] = torch.as_tensor(ep["action"], dtype=torch.float32)
        rew[i, :t, 0] = torch.as_tensor(ep["reward"], dtype=torch.float32)
        succ[i, :t, 0] = torch.as_tensor(ep["success"])
        state[i, :t] = torch.as_tensor(ep["state"], dtype=torch.float32)
        mask[i, :t] = True
    last = mask & ~torch.cat([mask[:, 1:], torch.zeros_like(mask[:, :1])], 1)
    td = TensorDict(
        {
            "observation": obs,
            "action": act,
            "state": state,
            "mask": mask,
            "next": {
                "observation": nxt,
                "reward": rew,
                "success": succ,
                "done": last[..., None].clone(),
                "terminated": torch.zeros(n, horizon, 1, dtype=torch.bool),
                "truncated": last[..., None].clone(),
            },
        },
        batch_size=[n, horizon],
    )
    per_traj = TensorDict(
        {
            "group": torch.tensor([ep["group"] for ep in episodes], dtype=torch.int64),
            "episode": torch.tensor([ep["episode"] for ep in episodes], dtype=torch.int64),
            "policy_task": torch.tensor([ep["policy_task"] for ep in episodes], dtype=torch.int64),
        },
        batch_size=[n],
    )
    return td, per_traj


def check_groups(groups) -> list[str]:
    """``groups`` as a list in :data:`GROUPS` order; a clear ``ValueError`` if empty, repeated or unknown.

    Example:
        >>> check_groups(["random", "expert"])
        ['expert', 'random']
    """
    if isinstance(groups, str):
        groups = [groups]
    groups = [str(g) for g in groups]
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise ValueError(f"groups: unknown group(s) {unknown}; choose from {list(GROUPS)}")
    if not groups or len(set(groups)) != len(groups):
        raise ValueError(f"groups: need one or more distinct groups of {list(GROUPS)}, got {groups}")
    return [g for g in GROUPS if g in groups]


def _config(task, episodes_per_group, noise, seed, max_steps, groups=GROUPS) -> dict:
    import importlib.metadata

    return {
        "task": task,
        "episodes_per_group": int(episodes_per_group),
        "noise": float(noise),
        "seed": int(seed),
        "max_steps": int(max_steps),
        "groups": check_groups(groups),  # all four: the key (and cache path) of earlier versions
        "success_streak": SUCCESS_STREAK,
        "action_clip": ACTION_CLIP,
        "generator": "torchrl_ftb.datasets.metaworld",
        "generator_version": GENERATOR_VERSION,
        "metaworld_version": importlib.metadata.version("metaworld"),
    }


def _cache_path(cache_dir: Path, config: dict) -> Path:
    digest = hashlib.sha1(json.dumps(config, sort_keys=True).encode()).hexdigest()[:12]
    name = f"metaworld-{config['task']}-n{config['episodes_per_group']}-eps{config['noise']:g}-seed{config['seed']}"
    return cache_dir / f"{name}-{digest}"


def make_metaworld_dataset(
    task: str,
    *,
    episodes_per_group: int = 100,
    noise: float = 1.0,
    seed: int = 0,
    max_steps: int = METAWORLD_MAX_EPISODE_STEPS,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
    num_workers: int = 1,
    groups: "list[str] | tuple[str, ...]" = GROUPS,
) -> tuple[TensorDict, dict]:
    """Generate (or load from the cache) an IPL-style Meta-World dataset.

    Args:
        task: Meta-World v3 task, e.g. ``"button-press-v3"``.
        episodes_per_group: episodes in each of the 4 groups (``GROUPS``).
        noise: std ``ε`` of the Gaussian action noise (expert/within/cross).
        seed: dataset seed (fixes goals, noise, cross-policy choice).
        max_steps: time limit and padded horizon ``H``.
        cache_dir: cache folder (default :func:`default_cache_dir`); the cache key includes
            the whole config and the generator version.
        progress: show a tqdm bar.
        num_workers: worker processes (results are identical for any value).
        groups: which of :data:`GROUPS` to generate (default all four). An episode's
            randomness depends only on ``(seed, group, episode)``, so a subset holds exactly
            those groups' episodes of the full dataset (e.g. ``("expert", "within", "random")``
            drops the cross-env episodes, whose returns can exceed the expert's).

    Returns:
        ``(td, meta)``: the ``[len(groups) * episodes_per_group, max_steps]`` trajectory batch (keys of
        ``docs/conventions.md`` incl. ``("next", "success")`` and ``"state"``; ordered by group
        then episode) and the metadata dict of ``meta.json`` plus ``meta["path"]`` and
        ``meta["per_trajectory"]``, an ``[N]`` TensorDict with ``"group"`` (index into
        ``meta["groups"]``), ``"episode"`` and ``"policy_task"`` (index into
        :func:`~torchrl_ftb.envs.metaworld_tasks` of the acting scripted policy, -1 = random).

    Raises:
        ValueError: unknown task or bad option.
    """
    check_metaworld_task(task)
    if episodes_per_group < 1:
        raise ValueError(f"episodes_per_group must be >= 1, got {episodes_per_group}")
    if noise < 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    if num_workers < 1:
        raise ValueError(f"num_workers must be >= 1, got {num_workers}")
    config = _config(task, episodes_per_group, noise, seed, max_steps, groups)
    path = _cache_path(Path(cache_dir).expanduser() if cache_dir else default_cache_dir(), config)
    if (path / "meta.json").exists():
        td, meta, per = load_trajectories(path, with_per_trajectory=True)
        return td, {**meta, "path": str(path), "per_trajectory": per}

    jobs = [(GROUPS.index(g), e) for g in config["groups"] for e in range(episodes_per_group)]
    start = time.perf_counter()
    episodes = _generate(task, jobs, config, progress=progress, num_workers=num_workers)
    seconds = time.perf_counter() - start
    episodes.sort(key=lambda ep: (ep["group"], ep["episode"]))
    td, per = _to_trajectories(episodes, max_steps)
    # per["group"] indexes meta["groups"] (the selected groups), as dataset_stats and the benches read it
    per.set("group", torch.tensor([config["groups"].index(GROUPS[g]) for g in per.get("group").tolist()],
                                  dtype=torch.int64))
    meta = {
        "env_id": task,
        "domain": "metaworld",
        **config,
        "state_dim": int(td.get("state").shape[-1]),
        "generation_seconds": round(seconds, 2),
        "num_workers": num_workers,
        "machine": platform.platform(),
    }
    save_trajectories(td, path, meta=meta, per_trajectory=per)
    td, meta, per = load_trajectories(path, with_per_trajectory=True)
    return td, {**meta, "path": str(path), "per_trajectory": per}


def _generate(task: str, jobs: list, config: dict, *, progress: bool, num_workers: int) -> list[dict]:
    kw = dict(seed=config["seed"], noise=config["noise"], max_steps=config["max_steps"])
    bar = tqdm(total=len(jobs), desc=f"{task} episodes", disable=not progress)
    episodes: list[dict] = []
    if num_workers == 1:
        episodes = generate_metaworld_episodes(task, jobs, **kw, on_episode=lambda: bar.update(1))
    else:
        chunk = max(1, min(10, len(jobs) // (4 * num_workers)))
        # interleave groups so workers get similar loads (random/cross episodes are longer)
        order = sorted(jobs, key=lambda j: (j[1], j[0]))
        chunks = [order[i:i + chunk] for i in range(0, len(order), chunk)]
        with ProcessPoolExecutor(num_workers, mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(generate_metaworld_episodes, task, c, **kw) for c in chunks]
            for fut in as_completed(futures):
                res = fut.result()
                episodes.extend(res)
                bar.update(len(res))
    bar.close()
    return episodes


def dataset_stats(td: TensorDict, per_traj: TensorDict, *, groups: tuple | list = GROUPS) -> dict[str, dict]:
    """Per-group table: episodes, mean length, mean (undiscounted) return, success rate.

    An episode succeeds if ``("next", "success")`` is ever true. A final ``"all"`` row covers
    the whole dataset.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> td = make_toy_dataset(num_trajectories=4, horizon=8)
        >>> per = TensorDict({"group": torch.tensor([0, 0, 1, 1])}, batch_size=[4])
        >>> dataset_stats(td, per, groups=["a", "b"])["a"]["episodes"]
        2
    """
    mask = td.get("mask")
    group = per_traj.get("group")
    if group.shape != mask.shape[:1]:
        raise ValueError(f"per_traj['group']: shape {list(group.shape)} != [{mask.shape[0]}]")
    length = mask.sum(-1).float()
    ret = (td.get(("next", "reward")).squeeze(-1) * mask).sum(-1)
    if ("next", "success") in td.keys(True):
        succ = (td.get(("next", "success")).squeeze(-1) & mask).any(-1).float()
    else:
        succ = torch.full_like(length, float("nan"))
    rows = {}
    selections = [(name, group == i) for i, name in enumerate(groups)] + [("all", torch.ones_like(group, dtype=torch.bool))]
    for name, sel in selections:
        k = int(sel.sum())
        rows[name] = {
            "episodes": k,
            "mean_length": float(length[sel].mean()) if k else float("nan"),
            "mean_return": float(ret[sel].mean()) if k else float("nan"),
            "success_rate": float(succ[sel].mean()) if k else float("nan"),
        }
    return rows


def format_stats(stats: dict[str, dict]) -> str:
    """The table of :func:`dataset_stats` as aligned text."""
    lines = [f"{'group':<8} {'episodes':>8} {'mean_len':>9} {'mean_return':>12} {'success':>8}"]
    for name, row in stats.items():
        lines.append(f"{name:<8} {row['episodes']:>8d} {row['mean_length']:>9.1f} "
                     f"{row['mean_return']:>12.2f} {row['success_rate']:>8.2f}")
    return "\n".join(lines)


def _generate_for_registry(env: str, *, episodes_per_group: int = 100, noise: float = 1.0, seed: int = 0,
                           max_steps: int = METAWORLD_MAX_EPISODE_STEPS, out: str | None = None,
                           progress: bool = True, num_workers: int = 1,
                           groups: "list[str] | tuple[str, ...]" = GROUPS) -> tuple[TensorDict, dict]:
    return make_metaworld_dataset(env, episodes_per_group=episodes_per_group, noise=noise, seed=seed,
                                  max_steps=max_steps, cache_dir=out, progress=progress,
                                  num_workers=num_workers, groups=groups)


register_dataset_generator(
    "metaworld",
    _generate_for_registry,
    matches=lambda env: env in metaworld_tasks(),
    description="Meta-World v3 tasks, IPL recipe (expert/within/random/cross)",
)
