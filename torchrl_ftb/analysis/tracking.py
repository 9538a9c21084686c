"""Tracked replays: what a trajectory's *state path* is worth in the simulator, in closed loop (Meta-World, locomotion).

An open-loop replay (:mod:`torchrl_ftb.analysis.replay`) executes a generated trajectory's own actions. Over
hundreds of steps any action error compounds (the hand lags its mocap target), so a sample's states may be
a reachable path that its actions do not reach. This module reads the states as a plan, the way
Decision Diffuser executes its samples: a goal-conditioned inverse-dynamics controller, fitted on the
dataset's transitions (offline, no simulator), starts from the real start and at every step heads for the
hand position and gripper opening of the path's next state, from the state the simulator actually reached.
The simulator's return of that episode is the path's *tracked* return.

The tracker is imperfect, so a tracked return is compared only with another tracked return: the original
top-k is tracked too, and :func:`tracked_improvement` reports top-k → final set with both sides read the
same way, beside how closely the tracker reproduces the recorded top-k (its fidelity). The simulator is
used only for this reading, never by the flow. The tracker is :class:`torchrl_ftb.policy.PathTracker`
(:func:`torchrl_ftb.policy.fit_path_tracker`). Only generated Meta-World datasets carry the goals and starts
this needs.

Locomotion (:func:`locomotion_tracked_improvement`) needs neither a learned tracker nor recorded starts: its
observation is the simulator state up to the x position, so a shooting controller with the simulator as its
model (:func:`torchrl_ftb.envs.track_locomotion_paths`, greedy or with a lookahead) follows each path from its own
first state. It reproduces a path the simulator can follow exactly (a recorded one), so there the tracked top-k is
the recorded one, and a generated path's tracked return says how much of what its states claim any action sequence
reaches (a lower bound: the shooting looks ``lookahead`` steps ahead; on the 1,500-step hopper samples of
BENCHMARKS.md's session 35, 20 steps of lookahead tracked 161 where one step tracked 114, of 276 claimed).
"""
from __future__ import annotations

import zlib
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_ftb.analysis.replay import (
    checked_final_set,
    ended_early,
    episode_jobs,
    locomotion_paths,
    locomotion_sets,
    match_rows,
    metaworld_state_returns,
    nearest_start,
    replay_returns,
    samples_mean,
)
from torchrl_ftb.data.labels import true_return
from torchrl_ftb.datasets.metaworld import generate_metaworld_episodes
from torchrl_ftb.envs import MetaWorldShootingController, track_locomotion_paths
from torchrl_ftb.flow.flow import clip_actions, return_summary
from torchrl_ftb.policy.inverse_dynamics import PathTracker


def track_paths(task: str, jobs: list[tuple[int, int]], paths: torch.Tensor, lengths: list[int],
                tracker: PathTracker, *, seed: int, max_steps: int, on_episode=None,
                actions: torch.Tensor | None = None, candidates: int = 1, noise: float = 0.3,
                lookahead: int = 1, reader: int = 0) -> list[dict]:
    """Closed-loop tracked replays: each dataset episode's goal and start (``jobs``, :func:`episode_jobs`), then
    ``tracker`` heading for its path (``paths [K, H, D]`` observations, ``lengths`` valid steps each) until the
    data's stop rule or ``max_steps``. Returns per-step episodes, as
    :func:`~torchrl_ftb.datasets.metaworld.replay_metaworld_actions`.

    With ``candidates > 1`` each step shoots in the simulator instead
    (:class:`~torchrl_ftb.envs.MetaWorldShootingController`): the path's own action (``actions [K, H, 4]``),
    the tracker's and ``candidates - 2`` perturbations of it (std ``noise``), keeping the one that lands nearest
    the path's next hand, gripper and object. It reproduces a recorded path exactly; a generated one it follows
    greedily, one step at a time, which is no upper bound of its own actions or of the tracker (a nearer next
    state can lead off a path the own actions would have finished; ``lookahead > 1`` scores each candidate over
    that many steps, the controller's ``lookahead``). Each path's perturbations are seeded by
    ``seed``, the path's own numbers and ``reader`` (0: as before readers existed), so a path reads the same
    whatever is tracked with it, and another ``reader`` draws other perturbations of the same reading.

    Example:
        >>> eps = track_paths("button-press-v3", [(0, 0)], data["observation"][:1], [100], tracker,
        ...                   seed=0, max_steps=500)  # doctest: +SKIP
    """
    if len(jobs) != paths.shape[0] or len(lengths) != paths.shape[0]:
        raise ValueError(f"track_paths: {len(jobs)} jobs, {paths.shape[0]} paths and {len(lengths)} lengths; "
                         f"expected one of each per trajectory")
    if candidates > 1 and (actions is None or actions.shape[:2] != paths.shape[:2]):
        raise ValueError(f"track_paths: shooting with {candidates} candidates needs the paths' own actions "
                         f"[{paths.shape[0]}, {paths.shape[1]}, 4], got "
                         f"{None if actions is None else list(actions.shape)}")
    paths = paths.double().cpu().numpy()
    controllers = [tracker.controller(p, int(n)) for p, n in zip(paths, lengths)]
    if candidates > 1:
        acts = actions.double().cpu().numpy()
        controllers = [MetaWorldShootingController(
            p, int(n), own_actions=a, proposal=c, candidates=candidates, noise=noise, lookahead=lookahead,
            seed=(int(seed), zlib.crc32(p[:int(n)].tobytes() + a[:int(n)].tobytes()), *([int(reader)] if reader else [])))
            for p, a, n, c in zip(paths, acts, lengths, controllers)]
    return generate_metaworld_episodes(task, jobs, seed=seed, noise=0.0, max_steps=max_steps,
                                       on_episode=on_episode, controllers=controllers)


#: readings per generated path when a caller leaves ``readers`` unset (``None``) and shoots: one reading's
#: sweep-into success is a lottery (BENCHMARKS.md session 48), four were the benchmarks' reading from session 49 on
SHOOTING_READERS = 4


def check_readers(readers: int | None, candidates: int) -> int:
    """``readers`` as an int, checked against ``candidates`` (a whole number >= 1; :func:`tracked_improvement`):
    >= 1, and more than one reading needs shooting (``candidates > 1``; the tracker alone reads a path the same
    every time). ``None``: :data:`SHOOTING_READERS` with shooting, else 1. A ``ValueError`` otherwise; callers prefix the option names
    they take.

    Example:
        >>> check_readers(None, 4), check_readers(None, 1), check_readers(2, 4)
        (4, 1, 2)
    """
    if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
        raise ValueError(f"candidates={candidates!r}: must be a whole number >= 1 "
                         f"(1: the tracker alone)")
    if readers is None:
        return SHOOTING_READERS if candidates > 1 else 1
    if readers < 1:
        raise ValueError(f"readers={readers}: must be >= 1")
    if readers > 1 and candidates < 2:
        raise ValueError(f"more than one reading needs shooting (candidates={candidates}, need > 1; the tracker "
                         f"alone reads a path the same every time)")
    return int(readers)


def _hand_deviation(episodes: list[dict], paths: torch.Tensor, lengths: list[int]) -> list[float]:
    """Mean distance (m) between the tracked hand and the path's, over the steps both have."""
    out = []
    for ep, path, n in zip(episodes, paths, lengths):
        k = min(int(n), len(ep["observation"]))
        real = torch.as_tensor(ep["observation"][:k, 0:3], dtype=torch.float64)
        out.append(float((real - path[:k, 0:3].double()).norm(dim=-1).mean()))
    return out


def tracked_improvement(
    final: TensorDictBase,
    original: TensorDictBase,
    generated: torch.Tensor,
    data: TensorDictBase,
    meta: dict,
    *,
    task: str,
    horizon: int,
    tracker: PathTracker,
    original_rows: torch.Tensor | None = None,
    candidates: int = 1,
    noise: float = 0.3,
    lookahead: int = 1,
    readers: int | None = 1,
    progress: bool = False,
) -> dict:
    """The flow's improvement (original top-k -> final set) with every trajectory's states tracked in closed loop.

    Every original top-k trajectory is tracked from its own start, every generated one from the start of its
    nearest dataset episode (as :func:`~torchrl_ftb.analysis.open_loop_improvement`); the final set's
    originals reuse their top-k episodes. Both sides go through the same tracker, so the ratio is fair
    though the tracker is imperfect; ``fidelity`` says how imperfect on the top-k (tracked vs recorded).

    Args:
        final, original, generated, data, meta, task, horizon, original_rows: as
            :func:`~torchrl_ftb.analysis.open_loop_improvement`.
        tracker: from :func:`fit_path_tracker` on ``data``.
        candidates, noise: 1 (default): the tracker alone. More: shoot in the simulator (:func:`track_paths`),
            which reproduces the recorded top-k exactly and reads every path by a greedy choice, step by step,
            among its own action, the tracker's and perturbations. Its off-path bound is then the
            largest hand deviation of the tracker alone on the top-k (tracked again for it; ``fidelity``'s
            ``tracker_alone_*``).
        lookahead: with shooting, the steps each candidate action is scored over (1: greedy; :func:`track_paths`).
        readers: with shooting, read every generated path this many times, each with other perturbations
            (:func:`track_paths`' ``reader`` 0, 1, ...), and take its mean tracked return, success rate and hand
            deviation over the readings: a property of the path rather than of one reading's draws (on
            sweep-into one reading's success is a lottery, BENCHMARKS.md session 48). The top-k is read once:
            shooting reproduces a recorded path whatever the perturbations (its own action wins ties). ``None``:
            :func:`check_readers`' default (4 with shooting, else 1).
        progress: a progress bar over the episodes.

    Returns:
        ``tracked`` (``return_summary`` of the stop-rule return, top-k -> final, both tracked),
        ``tracked_on_path`` (the same without the final set's *off-path* generated samples: those the tracker
        left further than its largest hand deviation on the top-k, whose tracked return is the tracker's
        rather than the plan's), ``claimed`` (the same read off the states), ``fidelity`` (the top-k's
        recorded vs tracked mean, max and success rate, and the tracked hand's median and largest deviation
        from the recorded path), ``generated`` (count, median hand deviation, success rate, mean claimed and
        tracked return of the generated samples, how many are off path) and ``samples`` (per generated
        trajectory). With ``readers > 1`` the generated samples' numbers are means over the readings (a sample's
        ``tracked_success`` is its success rate, ``tracked_stop_rule_per_reader`` and
        ``hand_deviation_per_reader`` its readings), a sample is off path if any reading left it, and
        ``tracked_per_reader`` holds each reading's own ``return_summary``.

    Example:
        >>> tracker = fit_path_tracker(data)  # doctest: +SKIP
        >>> out = tracked_improvement(flow.trajectories, flow.original, flow.source_step > 0, data, meta,
        ...                           task="drawer-open-v3", horizon=500, tracker=tracker)  # doctest: +SKIP
        >>> out["tracked"]["true_return_mean_after"]  # doctest: +SKIP
    """
    try:
        readers = check_readers(readers, candidates)
    except ValueError as err:
        raise ValueError(f"tracked_improvement: {err}") from None
    final, original, generated = checked_final_set("tracked_improvement", task, final, original, generated, meta)
    data_obs = data["observation"]
    rows = match_rows(original["observation"].float(), data_obs) if original_rows is None else original_rows.cpu()
    gen = final[generated]
    start_row, _ = nearest_start(gen["observation"][:, 0].float(), data_obs[:, 0])
    paths = torch.cat([original["observation"], gen["observation"]], 0)
    actions = torch.cat([original["action"], gen["action"]], 0)
    lengths = [int(n) for n in torch.cat([original["mask"], gen["mask"]], 0).sum(-1).tolist()]
    jobs = episode_jobs(meta, torch.cat([rows, start_row]))
    k = original.batch_size[0]
    bar = tqdm(total=len(jobs) + (readers - 1) * (len(jobs) - k), desc=f"{task} tracked replays", disable=not progress)
    readings = []  # per reading: (tracked return, success, hand deviation) of the paths it read
    for reader in range(readers if len(jobs) > k else 1):  # nothing generated: one reading of the top-k
        part = slice(0 if reader == 0 else k, None)
        episodes = track_paths(task, jobs[part], paths[part], lengths[part], tracker, seed=int(meta["seed"]),
                               max_steps=int(meta["max_steps"]), on_episode=lambda: bar.update(1),
                               actions=actions[part], candidates=candidates, noise=noise, lookahead=lookahead,
                               reader=reader)
        readings.append((replay_returns(episodes, horizon=horizon)[:, 1],
                         torch.tensor([float(ep["success"].any()) for ep in episodes], dtype=torch.float64),
                         torch.tensor(_hand_deviation(episodes, paths[part], lengths[part]), dtype=torch.float64)))
    bar.close()
    generated_reads = [tuple(x[k:] for x in readings[0])] + readings[1:]
    tracked, success, deviation = (torch.cat([readings[0][i][:k], torch.stack([g[i] for g in generated_reads]).mean(0)])
                                   for i in range(3))
    by_row = dict(zip(rows.tolist(), tracked[:k].tolist()))
    final_rows = match_rows(final[~generated]["observation"].float(), data_obs) if bool((~generated).any()) else []
    missing = [int(r) for r in torch.as_tensor(final_rows).tolist() if int(r) not in by_row]
    if missing:
        raise ValueError(f"tracked_improvement: final-set originals {missing[:5]} are not in the original top-k")
    after = torch.zeros(final.batch_size[0], dtype=torch.float64)
    after[~generated] = torch.tensor([by_row[int(r)] for r in torch.as_tensor(final_rows).tolist()], dtype=torch.float64)
    after[generated] = tracked[k:]
    claimed0 = metaworld_state_returns(task, clip_actions(original.clone(), 1.0), horizon=horizon)[:, 2]
    claimed1 = metaworld_state_returns(task, clip_actions(final.clone(), 1.0), horizon=horizon)[:, 2]
    recorded = true_return(data, horizon=horizon).double()[rows]
    data_success = data["next", "success"].any(-2).reshape(-1)[rows] if ("next", "success") in data.keys(True) else None
    fidelity = {"recorded_mean": float(recorded.mean()), "tracked_mean": float(tracked[:k].mean()),
                "recorded_max": float(recorded.max()), "tracked_max": float(tracked[:k].max()),
                "tracked_success_rate": float(success[:k].double().mean()),
                "recorded_success_rate": None if data_success is None else float(data_success.double().mean()),
                "hand_deviation_median": float(deviation[:k].median()),
                "hand_deviation_max": float(deviation[:k].max())}
    # a generated path the tracker left further than it ever leaves a real one: its tracked return is the
    # tracker's doing, not the plan's (README run: claimed 89, 9.9 cm off, tracked 4293, BENCHMARKS #5)
    limit = fidelity["hand_deviation_max"]
    if candidates > 1:  # shooting reproduces real paths exactly: the bound is how far the tracker alone strays
        alone = track_paths(task, jobs[:k], paths[:k], lengths[:k], tracker, seed=int(meta["seed"]),
                            max_steps=int(meta["max_steps"]))
        alone_dev = torch.tensor(_hand_deviation(alone, paths[:k], lengths[:k]), dtype=torch.float64)
        limit = float(alone_dev.max())
        fidelity.update(tracker_alone_tracked_mean=float(replay_returns(alone, horizon=horizon)[:, 1].mean()),
                        tracker_alone_hand_deviation_max=limit)
    off_path = torch.zeros(final.batch_size[0], dtype=torch.bool)
    # off path if any reading left it (a mean over the readings could hide the one whose return is the tracker's)
    off_path[generated] = torch.stack([g[2] for g in generated_reads]).gt(limit).any(0)
    samples = [{"start_row": int(r), "length": int(n), "claimed_stop_rule": float(c), "tracked_stop_rule": float(t),
                "tracked_success": bool(s) if readers == 1 else float(s), "hand_deviation": float(d)}
               for r, n, c, t, s, d in zip(start_row.tolist(), lengths[k:], claimed1[generated], tracked[k:],
                                           success[k:], deviation[k:])]
    per_reader = []
    if readers > 1:
        for i, sample in enumerate(samples):
            sample["tracked_stop_rule_per_reader"] = [float(g[0][i]) for g in generated_reads]
            sample["hand_deviation_per_reader"] = [float(g[2][i]) for g in generated_reads]
        for g in generated_reads:
            after_r = after.clone()
            after_r[generated] = g[0]
            per_reader.append(return_summary(tracked[:k], after_r))
    n_gen = len(samples)
    gen_summary = {"num_generated": n_gen,
                   "hand_deviation_median": float(deviation[k:].median()) if n_gen else None,
                   "tracked_success_rate": float(success[k:].double().mean()) if n_gen else None,
                   "claimed_stop_rule_mean": float(claimed1[generated].mean()) if n_gen else None,
                   "tracked_stop_rule_mean": float(tracked[k:].mean()) if n_gen else None,
                   "off_path": int(off_path.sum())}
    return {"horizon": horizon,
            "shooting": {"candidates": int(candidates), "noise": float(noise), "lookahead": int(lookahead),
                         "readers": int(readers)},
            "tracked": return_summary(tracked[:k], after),
            "tracked_on_path": (return_summary(tracked[:k], after[~off_path]) if bool((~off_path).any())
                                else {key: float("nan") for key in return_summary(tracked[:k], tracked[:k])}),
            "claimed": return_summary(claimed0, claimed1), "fidelity": fidelity, "generated": gen_summary,
            "samples": samples, **({"tracked_per_reader": per_reader} if readers > 1 else {})}


def observation_scale(trajs: TensorDictBase) -> torch.Tensor:
    """``float64 [obs_dim]``: the per-dimension std of ``trajs``' valid observations (floored at 1e-6), the distance
    scale of the locomotion tracker (:func:`locomotion_tracked_returns`)."""
    return trajs["observation"][trajs["mask"]].double().std(0).clamp_min(1e-6)


def locomotion_tracked_returns(env_name: str, trajs: TensorDictBase, *, scale: torch.Tensor | None = None,
                               candidates: int = 64, noise: float = 0.3, uniform: float = 0.5, lookahead: int = 1,
                               seed: int = 0) -> tuple[torch.Tensor, list[dict]]:
    """Closed-loop tracked returns of locomotion trajectories (``observation``, ``action``, ``mask``; ``[N, H]``):
    the tracked counterpart of :func:`~torchrl_ftb.analysis.locomotion_replays`.

    Each path is tracked from the state of its own first observation by
    :func:`~torchrl_ftb.envs.track_locomotion_paths` (actions clipped to ``[-1, 1]``; ``candidates``, ``noise``,
    ``uniform``, ``lookahead``, ``seed`` as there), until it ends or the env ends the episode.

    Args:
        env_name: the locomotion env.
        trajs: the trajectories.
        scale: ``[obs_dim]`` the distance's per-dimension scale; default :func:`observation_scale` of ``trajs``.
            Pass one scale to read several sets alike (:func:`locomotion_tracked_improvement` uses the top-k's).

    Returns:
        ``(returns float64 [N], episodes)``: the tracked episodes' plain returns and their per-step records.

    Example:
        >>> from torchrl_ftb.envs import make_locomotion_env
        >>> td = make_locomotion_env("hopper", seed=0).rollout(8)
        >>> trajs = td.select("observation", "action").unsqueeze(0)
        >>> trajs["mask"] = torch.ones(1, 8, dtype=torch.bool)
        >>> returns, _ = locomotion_tracked_returns("hopper", trajs, candidates=4)
        >>> abs(float(returns[0]) - float(td["next", "reward"].sum())) < 1e-3
        True
    """
    t = locomotion_paths(trajs)
    return _tracked_returns(env_name, t, scale=observation_scale(t) if scale is None else torch.as_tensor(scale).cpu(),
                            candidates=candidates, noise=noise, uniform=uniform, lookahead=lookahead, seed=seed)


def _tracked_returns(env_name: str, t: TensorDictBase, *, scale: torch.Tensor,
                     **options) -> tuple[torch.Tensor, list[dict]]:
    """:func:`locomotion_tracked_returns` of paths already prepared by
    :func:`~torchrl_ftb.analysis.replay.locomotion_paths` (so the readings that prepare their sets once do not
    copy and clip them again)."""
    lengths = [int(n) for n in t["mask"].sum(-1).tolist()]
    eps = track_locomotion_paths(env_name, t["observation"], t["action"], lengths, scale=scale, **options)
    return torch.tensor([float(ep["reward"].sum()) for ep in eps], dtype=torch.float64), eps


class TrackedTopK(NamedTuple):
    """A top-k tracked once (:func:`track_top_k`), to read several final sets against it with
    :func:`locomotion_tracked_improvement` (``original_tracked=``) without tracking it again.

    It carries what it was tracked from and how, so a reading with other trajectories, another env or other tracker
    options is refused instead of mixing two trackers' numbers."""

    returns: torch.Tensor
    episodes: list[dict]
    observation: torch.Tensor
    mask: torch.Tensor
    options: dict


def _tracker_options(env_name: str, *, candidates: int, noise: float, uniform: float, lookahead: int,
                     seed: int) -> dict:
    return {"env_name": env_name, "candidates": int(candidates), "noise": float(noise), "uniform": float(uniform),
            "lookahead": int(lookahead), "seed": int(seed)}


def track_top_k(env_name: str, original: TensorDictBase, *, candidates: int = 64, noise: float = 0.3,
                uniform: float = 0.5, lookahead: int = 1, seed: int = 0) -> TrackedTopK:
    """The top-k ``original`` tracked the way :func:`locomotion_tracked_improvement` tracks it (actions clipped,
    distance scaled by its own :func:`observation_scale`), with its options recorded.

    Example:
        >>> from torchrl_ftb.envs import make_locomotion_env
        >>> td = make_locomotion_env("hopper", seed=0).rollout(8)
        >>> trajs = td.select("observation", "action").unsqueeze(0)
        >>> trajs["mask"] = torch.ones(1, 8, dtype=torch.bool)
        >>> top = track_top_k("hopper", trajs, candidates=4)
        >>> out = locomotion_tracked_improvement(trajs, trajs, torch.tensor([True]), env_name="hopper", candidates=4,
        ...                                      original_tracked=top)
        >>> out["tracked"]["true_return_mean_before"] == float(top.returns[0])
        True
    """
    options = _tracker_options(env_name, candidates=candidates, noise=noise, uniform=uniform, lookahead=lookahead,
                               seed=seed)
    t = locomotion_paths(original)
    returns, episodes = _tracked_returns(env_name, t, scale=observation_scale(t), candidates=candidates, noise=noise,
                                         uniform=uniform, lookahead=lookahead, seed=seed)
    return TrackedTopK(returns, episodes, t["observation"], t["mask"], options)


def _checked_top_tracked(given: TrackedTopK, top: TensorDictBase, options: dict) -> TrackedTopK:
    """``given`` if it was tracked from ``top`` with ``options``, else a ValueError naming what differs."""
    name = "locomotion_tracked_improvement: original_tracked"
    if not isinstance(given, TrackedTopK):
        raise TypeError(f"{name} must be a TrackedTopK (track_top_k), got {type(given).__name__}")
    differ = {k: (given.options.get(k), v) for k, v in options.items() if given.options.get(k) != v}
    if differ:
        raise ValueError(f"{name} was tracked with other options: "
                         + ", ".join(f"{k}={a!r} there, {b!r} here" for k, (a, b) in differ.items()))
    same = all(a.shape == b.shape and torch.equal(a, b)
               for a, b in ((given.observation, top["observation"]), (given.mask, top["mask"])))
    if not same:
        raise ValueError(f"{name} was tracked from other trajectories than this top-k: their observations or masks "
                         f"differ (observations {tuple(given.observation.shape)} there, "
                         f"{tuple(top['observation'].shape)} here)")
    return given


def locomotion_tracked_improvement(final: TensorDictBase, original: TensorDictBase, generated: torch.Tensor, *,
                                   env_name: str, candidates: int = 64, noise: float = 0.3, uniform: float = 0.5,
                                   lookahead: int = 1, seed: int = 0, progress: bool = False,
                                   original_tracked: TrackedTopK | None = None) -> dict:
    """The flow's improvement (original top-k -> final set) on locomotion with every path tracked in closed loop.

    Every trajectory of both sets is tracked from its own first state by
    :func:`~torchrl_ftb.envs.track_locomotion_paths` (``candidates``, ``noise``, ``uniform``, ``lookahead``,
    ``seed``), the distance scaled by the top-k's per-dimension observation std; the return is the simulator's
    over the steps until the path ends or the env ends the episode.

    Args:
        final, original, generated, env_name, progress: as
            :func:`~torchrl_ftb.analysis.locomotion_open_loop_improvement`.
        original_tracked: the top-k already tracked, :func:`track_top_k` of ``original`` with this call's
            ``env_name`` and tracker options (checked: other options or other trajectories raise), to read
            several final sets against one top-k without tracking it again; default: tracked here.

    Returns:
        ``horizon`` (None: plain returns), ``lookahead``, ``tracked`` and ``claimed`` (``return_summary``, top-k ->
        final),
        ``fidelity`` (the top-k's claimed vs tracked mean and median scaled path error: ~0 for recorded paths),
        ``generated`` (count, median scaled path error, share the env ended early, mean claimed and tracked
        return) and ``samples`` (per generated trajectory).

    Example:
        >>> from torchrl_ftb.envs import make_locomotion_env
        >>> td = make_locomotion_env("hopper", seed=0).rollout(8)
        >>> trajs = td.select("observation", "action").unsqueeze(0)
        >>> trajs["mask"] = torch.ones(1, 8, dtype=torch.bool)
        >>> out = locomotion_tracked_improvement(trajs, trajs, torch.tensor([True]), env_name="hopper", candidates=4)
        >>> abs(out["tracked"]["true_return_mean_after"] - float(td["next", "reward"].sum())) < 1e-3
        True
    """
    generated, sets, claimed = locomotion_sets("locomotion_tracked_improvement", env_name, final, original, generated)
    scale = observation_scale(sets[0])
    if original_tracked is not None:
        options = _tracker_options(env_name, candidates=candidates, noise=noise, uniform=uniform,
                                   lookahead=lookahead, seed=seed)
        original_tracked = _checked_top_tracked(original_tracked, sets[0], options)
    tracked, episodes = [], []
    for t, given in tqdm(zip(sets, (original_tracked, None)), total=len(sets),
                         desc=f"{env_name} tracked paths (top-k, final set)", disable=not progress):
        returns, eps = given[:2] if given is not None else _tracked_returns(
            env_name, t, scale=scale, candidates=candidates, noise=noise, uniform=uniform, lookahead=lookahead,
            seed=seed)
        tracked.append(returns)
        episodes.append(list(zip([int(n) for n in t["mask"].sum(-1).tolist()], eps)))

    def path_error(ep: dict) -> float:
        return float(ep["path_error"].mean()) if len(ep["path_error"]) else 0.0

    samples = [{"length": n, "tracked_length": len(ep["reward"]), "tracked_terminated": ended_early(ep, n),
                "path_error": path_error(ep), "claimed_plain": float(claimed[1][i]), "tracked_plain": float(tracked[1][i])}
               for i, (n, ep) in ((i, episodes[1][i]) for i in generated.nonzero().squeeze(-1).tolist())]
    n_gen = len(samples)

    fidelity = {"claimed_mean": float(claimed[0].mean()), "tracked_mean": float(tracked[0].mean()),
                "path_error_median": float(torch.tensor([path_error(ep) for _, ep in episodes[0]]).median())}
    gen_summary = {"num_generated": n_gen,
                   "path_error_median": float(torch.tensor([x["path_error"] for x in samples]).median()) if n_gen else None,
                   "tracked_terminated_rate": samples_mean(samples, "tracked_terminated"),
                   "claimed_plain_mean": samples_mean(samples, "claimed_plain"),
                   "tracked_plain_mean": samples_mean(samples, "tracked_plain")}
    return {"horizon": None, "lookahead": int(lookahead), "tracked": return_summary(*tracked),
            "claimed": return_summary(*claimed),
            "fidelity": fidelity, "generated": gen_summary, "samples": samples}
