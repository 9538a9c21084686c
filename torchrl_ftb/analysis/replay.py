"""Open-loop replays: what a generated trajectory's actions do in the simulator (Meta-World and locomotion).

The flow's "true return" of a generated trajectory is the task's reward read off its *generated*
observations (:func:`torchrl_ftb.envs.true_reward_fn`): what the diffuser claims happened, not what
executing its actions achieves. This module asks the simulator. Every generated trajectory of a final set
is replayed from the start of the dataset episode nearest to its first observation (a sample edits, or is
conditioned on, a trajectory that starts there): that episode's own goal and reset, then the sample's
actions open loop, with the data's stop rule (:func:`torchrl_ftb.datasets.metaworld.replay_metaworld_actions`;
replaying a recorded episode's actions reproduces it, tested). After the sample's last action the hand
holds still (zero actions) until the stop rule or the time limit, as an episode runs on.

The "replayed" improvement compares the simulator's own returns: recorded rewards for dataset trajectories
(the original top-k, the final set's originals) and the replays for generated ones. The "claimed" one reads
every return off the states, as the flow's statistics do. Returns are the plain sum and the stop-rule
return (fill to ``horizon`` steps where the stop rule, ``SUCCESS_STREAK`` consecutive successes, ended
the trajectory; one that ran out of actions or time earns its own steps only). Open-loop replay is the
strictest reading: a policy cloned from a sample acts in closed loop.

Only generated Meta-World datasets (:func:`torchrl_ftb.datasets.make_metaworld_dataset`) carry the goals
and starts this needs. Locomotion needs neither: its observation is the simulator state up to the x position,
which the dynamics ignore, so :func:`locomotion_open_loop_improvement` replays every trajectory of both sets
from the state rebuilt from its own first observation (:func:`torchrl_ftb.envs.replay_locomotion_actions`), until
its actions run out or the env terminates it (Hopper / Walker2d fall). There "claimed" is the flow's own
reading, the exact per-transition reward of each generated ``(s, a)`` (:func:`torchrl_ftb.envs.locomotion_true_reward`),
which a state the trajectory never reaches still earns.
"""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_ftb.data import stop_rule_fill
from torchrl_ftb.data.labels import true_return
from torchrl_ftb.datasets.metaworld import GROUPS, SUCCESS_STREAK, replay_metaworld_actions
from torchrl_ftb.envs import metaworld_hand_object_distance, replay_locomotion_actions, true_reward_fn
from torchrl_ftb.flow.flow import clip_actions, masked_true_returns, return_summary

#: a sample "starts at" a dataset episode when its first observation is this close (max-abs, metres)
START_TOLERANCE = 0.01


def metaworld_state_returns(task: str, trajs: TensorDictBase, *, horizon: int) -> torch.Tensor:
    """``float64 [N, 3]`` true returns read off Meta-World trajectories' states: plain, with the stop-rule
    fill to ``horizon`` steps, and the same fill after cutting each trajectory where our episodes' stop rule
    (``SUCCESS_STREAK`` consecutive successes) would have ended it -- the data were cut there when recorded,
    generated trajectories were not. One rewarder pass per trajectory; the recipe's flow statistics use the
    same definitions (``flow.true_return_horizon`` / ``flow.true_return_streak``).

    Example:
        >>> from torchrl_ftb.datasets import make_metaworld_dataset
        >>> data, _ = make_metaworld_dataset("button-press-v3", episodes_per_group=1)  # doctest: +SKIP
        >>> metaworld_state_returns("button-press-v3", data, horizon=500).shape  # doctest: +SKIP
        torch.Size([4, 3])
    """
    return masked_true_returns(trajs, true_reward_fn(task, with_success=True), horizons=(None, horizon, horizon),
                               streaks=(None, None, SUCCESS_STREAK))


def match_rows(observation: torch.Tensor, data_observation: torch.Tensor) -> torch.Tensor:
    """Dataset row of each trajectory that is one of the dataset's (``observation [K, H, D]`` vs ``[N, H, D]``).

    Example:
        >>> data = torch.randn(5, 3, 2)
        >>> match_rows(data[[4, 1]], data).tolist()
        [4, 1]
    """
    flat_o, flat_d = observation.flatten(1), data_observation.flatten(1)
    idx = torch.cdist(flat_o, flat_d).argmin(-1)
    if not torch.allclose(flat_d[idx], flat_o):
        raise ValueError("match_rows: the trajectories are not rows of the dataset (another dataset or run?)")
    return idx


def nearest_start(first: torch.Tensor, data_first: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Dataset row whose first observation is nearest to each sample's (Euclidean), and the distance to it
    (max-abs, what :data:`START_TOLERANCE` bounds).

    The Euclidean distance picks the row: a coordinate every dataset start shares (Meta-World's hand start, a
    fixed goal) adds the same to every row, so the choice rests on the coordinates that tell episodes apart (the
    object's and the goal's positions). The max-abs distance picked rows until session 45: a sample whose hand
    starts a few centimetres off the common start was that far from *every* row, the tie went to row 0, and
    most samples were replayed with another episode's object position.

    Example:
        >>> rows, dist = nearest_start(torch.tensor([[0.0, 1.0]]), torch.tensor([[5.0, 5.0], [0.0, 1.0]]))
        >>> rows.tolist(), dist.tolist()
        ([1], [0.0])
        >>> # the first coordinate is shared by every start: the second decides (max-abs would tie at 0.5)
        >>> nearest_start(torch.tensor([[0.5, 0.15]]), torch.tensor([[0.0, 0.0], [0.0, 0.2]]))[0].tolist()
        [1]
    """
    rows = torch.cdist(first.double(), data_first.double()).argmin(-1)
    return rows, (first - data_first[rows]).abs().amax(-1)


def episode_jobs(meta: dict, rows: torch.Tensor) -> list[tuple[int, int]]:
    """``(group index, episode)`` of dataset rows of a generated Meta-World dataset (its ``meta``): the jobs
    that re-create those episodes' goals and starts (:func:`~torchrl_ftb.datasets.metaworld.replay_metaworld_actions`).

    Example:
        >>> meta = {"groups": ["expert", "random"], "per_trajectory": {"group": [1, 0], "episode": [7, 3]}}
        >>> episode_jobs(meta, torch.tensor([1]))
        [(0, 3)]
    """
    per, groups = meta["per_trajectory"], list(meta["groups"])
    return [(GROUPS.index(groups[int(per["group"][r])]), int(per["episode"][r])) for r in torch.as_tensor(rows).tolist()]


def replay_returns(episodes: list[dict], *, horizon: int) -> torch.Tensor:
    """``float64 [N, 2]``: plain sum and stop-rule return of open-loop replays (filled to ``horizon`` only
    where the stop rule, ``SUCCESS_STREAK`` consecutive successes, ended the replay).

    Example:
        >>> import numpy as np
        >>> ep = {"reward": np.ones(3), "success": np.zeros(3, bool)}  # ran out of actions: no fill
        >>> replay_returns([ep], horizon=10).tolist()
        [[3.0, 3.0]]
    """
    out = torch.zeros(len(episodes), 2, dtype=torch.float64)
    for i, ep in enumerate(episodes):
        reward = torch.as_tensor(ep["reward"], dtype=torch.float64)
        success = torch.as_tensor(ep["success"], dtype=torch.bool)
        n = reward.numel()
        fired = n >= SUCCESS_STREAK and bool(success[-SUCCESS_STREAK:].all())  # the replay stops at the streak
        # the project's one fill rule (stop_rule_fill); a replay no stop rule ended counts as terminated there
        ended = torch.zeros(1, n, dtype=torch.bool)
        ended[0, -1] = not fired
        last, weight = stop_rule_fill(torch.ones(1, n, dtype=torch.bool), horizon=horizon, terminated=ended)
        out[i, 0] = reward.sum()
        out[i, 1] = reward.sum() + float(weight[0]) * float(reward[last[0]])
    return out


def checked_final_set(name: str, task: str, final: TensorDictBase, original: TensorDictBase, generated: torch.Tensor,
                      meta: dict) -> tuple[TensorDictBase, TensorDictBase, torch.Tensor]:
    """The simulator readings' shared input check: a generated Meta-World dataset (its goals and starts) and one
    ``generated`` flag per final-set trajectory; returns ``(final, original, generated)`` on CPU, trajectory keys only.

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.zeros(2, 3, 39), "action": torch.zeros(2, 3, 4),
        ...                  "mask": torch.ones(2, 3, dtype=torch.bool)}, [2, 3])
        >>> checked_final_set("f", "t", td, td, torch.tensor([1, 0]), {"domain": "metaworld", "per_trajectory": {}})[2]
        tensor([ True, False])
    """
    if meta.get("domain") != "metaworld" or "per_trajectory" not in meta:
        raise ValueError(f"{name}: {task}'s dataset is not a generated Meta-World one "
                         f"(its goals and starts are needed to replay from them)")
    keys = ("observation", "action", "mask")
    return final.select(*keys).to("cpu"), original.select(*keys).to("cpu"), checked_generated(name, final, generated)


def checked_generated(name: str, final: TensorDictBase, generated: torch.Tensor) -> torch.Tensor:
    """``generated`` as a CPU bool tensor, one flag per final-set trajectory, or a ``ValueError`` naming ``name``."""
    generated = torch.as_tensor(generated, dtype=torch.bool).cpu()
    if generated.shape != final.batch_size[:1]:
        raise ValueError(f"{name}: generated has shape {list(generated.shape)}, "
                         f"expected [{final.batch_size[0]}] (one flag per final-set trajectory)")
    return generated


def ended_early(episode: dict, length: int) -> bool:
    """Whether the env ended a locomotion replay or track (``episode["terminated"]``) before its trajectory's
    ``length`` steps ran out (ending on the last step is not early).

    Example:
        >>> import numpy as np
        >>> fell = {"reward": np.zeros(3), "terminated": True}  # ended by the env after 3 steps
        >>> ended_early(fell, 10), ended_early(fell, 3)
        (True, False)
    """
    return bool(episode["terminated"] and len(episode["reward"]) < int(length))


def samples_mean(samples: list[dict], key: str) -> float | None:
    """Mean of ``key`` over per-sample dicts (None without samples)."""
    return float(np.mean([float(x[key]) for x in samples])) if samples else None


def locomotion_paths(trajs: TensorDictBase) -> TensorDictBase:
    """``trajs``' trajectory keys (``observation``, ``action``, ``mask``) on CPU, a copy, with actions clipped to
    ``[-1, 1]``: what every locomotion reading executes or tracks."""
    return clip_actions(trajs.select("observation", "action", "mask").to("cpu").clone(), 1.0)


def locomotion_sets(name: str, env_name: str, final: TensorDictBase, original: TensorDictBase,
                    generated: torch.Tensor) -> tuple[torch.Tensor, list[TensorDictBase], list[torch.Tensor]]:
    """The locomotion readings' shared input: ``(generated flags, [top-k, final set], their claimed returns)``, the
    sets on CPU with actions clipped to ``[-1, 1]`` and trajectory keys only, the claimed returns the exact reward of
    each ``(s, a)`` summed (``float64 [K]`` each)."""
    generated = checked_generated(name, final, generated)
    sets = [locomotion_paths(t) for t in (original, final)]
    reward_fn = true_reward_fn(env_name)
    return generated, sets, [masked_true_returns(t, reward_fn)[:, 0] for t in sets]


def open_loop_improvement(
    final: TensorDictBase,
    original: TensorDictBase,
    generated: torch.Tensor,
    data: TensorDictBase,
    meta: dict,
    *,
    task: str,
    horizon: int,
    original_rows: torch.Tensor | None = None,
    hold: bool = True,
    progress: bool = False,
) -> dict:
    """The flow's improvement (original top-k -> final set) claimed by the states and replayed in the simulator.

    Args:
        final: the final set (``observation``, ``action``, ``mask``; ``[K, H]``, unnormalised).
        original: the original top-k the flow started from (rows of ``data``).
        generated: ``bool [K]``, which final-set rows are generated (``source_step > 0``).
        data: the generated Meta-World dataset the run used (recorded rewards, successes, starts).
        meta: its metadata (:func:`~torchrl_ftb.datasets.make_metaworld_dataset`: ``seed``, ``max_steps``,
            ``groups``, ``per_trajectory``).
        task: the Meta-World v3 task.
        horizon: the stop-rule return's horizon (the time limit, 500).
        original_rows: dataset rows of ``original`` (``FlowResult.original_indices``); None: matched.
        hold: after a sample's last action, hold still (zero actions) until the stop rule or the time
            limit; False stops the replay there.
        progress: a progress bar over the replays.

    Returns:
        ``num_generated``, ``start_within_tolerance`` / ``start_distance_median`` (how far generated first
        observations are from the nearest dataset start), ``start_hand_object_median`` /
        ``data_start_hand_object_median`` (the hand-object distance at the samples' first step and at
        those dataset starts: a sample that starts nearer the object claims an easier task than its
        replay gets), ``replay_success_rate``, ``improvement``
        (``{"plain" | "stop_rule_<horizon>": {"claimed" | "replayed": return_summary}}``) and ``samples``
        (one dict per generated trajectory: lengths, start row and distance, claimed and replayed returns,
        whether the replay succeeded).

    Example:
        >>> out = open_loop_improvement(flow.trajectories, flow.original, flow.source_step > 0,
        ...                             data, meta, task="button-press-v3", horizon=500)  # doctest: +SKIP
        >>> out["improvement"]["stop_rule_500"]["replayed"]["true_return_mean_after"]  # doctest: +SKIP
    """
    final, original, generated = checked_final_set("open_loop_improvement", task, final, original, generated, meta)
    data_obs = data["observation"]
    # claimed: read off the states, as the flow's statistics (for recorded states too: exact up to the
    # rewarder's approximations, e.g. the last step's next observation, about 1 % on a return)
    claimed0 = metaworld_state_returns(task, clip_actions(original.clone(), 1.0), horizon=horizon)
    claimed1 = metaworld_state_returns(task, clip_actions(final.clone(), 1.0), horizon=horizon)
    # the simulator's own: recorded rewards for dataset trajectories, open-loop replays for generated ones
    recorded = torch.stack([true_return(data).double(), true_return(data, horizon=horizon).double()], -1)
    rows = match_rows(original["observation"].float(), data_obs) if original_rows is None else original_rows.cpu()
    real0 = recorded[rows]
    real1 = torch.zeros(final.batch_size[0], 2, dtype=torch.float64)
    if bool((~generated).any()):
        real1[~generated] = recorded[match_rows(final[~generated]["observation"].float(), data_obs)]
    gen = final[generated]
    start_row, start_dist = nearest_start(gen["observation"][:, 0].float(), data_obs[:, 0])
    jobs = episode_jobs(meta, start_row)
    lengths = gen["mask"].sum(-1).tolist()
    limit = int(meta["max_steps"])
    actions = [gen["action"][i, :n].numpy() for i, n in enumerate(lengths)]
    if hold:
        actions = [np.concatenate([a, np.zeros((limit - len(a), a.shape[-1]), dtype=a.dtype)]) for a in actions]
    bar = tqdm(total=len(jobs), desc=f"{task} open-loop replays", disable=not progress)
    episodes = replay_metaworld_actions(task, jobs, actions, seed=int(meta["seed"]), max_steps=limit,
                                        on_episode=lambda: bar.update(1)) if jobs else []
    bar.close()
    replayed = replay_returns(episodes, horizon=horizon)
    real1[generated] = replayed
    success = [bool(ep["success"].any()) for ep in episodes]
    # where a sample starts: how far its hand is from the object, beside the dataset start it is replayed from
    reach = metaworld_hand_object_distance(gen["observation"][:, 0].double())
    data_reach = metaworld_hand_object_distance(data_obs[start_row, 0].double())
    samples = [{"length": int(n), "replay_length": len(ep["reward"]), "start_row": int(r), "start_distance": float(d),
                "start_hand_object": float(h), "data_start_hand_object": float(hd),
                "claimed_plain": float(c[0]), "claimed_stop_rule": float(c[2]), "replayed_plain": float(p[0]),
                "replayed_stop_rule": float(p[1]), "replay_success": s}
               for n, ep, r, d, h, hd, c, p, s in zip(lengths, episodes, start_row.tolist(), start_dist.tolist(),
                                                      reach.tolist(), data_reach.tolist(), claimed1[generated],
                                                      replayed, success)]
    improvement = {name: {"claimed": return_summary(claimed0[:, c], claimed1[:, c]),
                          "replayed": return_summary(real0[:, j], real1[:, j])}
                   for j, c, name in ((0, 0, "plain"), (1, 2, f"stop_rule_{horizon}"))}
    return {"num_generated": len(samples), "hold_after_last_action": hold, "horizon": horizon,
            "start_tolerance": START_TOLERANCE, **summarize_samples(samples),
            "improvement": improvement, "samples": samples}


#: the summary fields :func:`summarize_samples` derives (None for a final set without generated trajectories)
SAMPLE_SUMMARY_KEYS = ("start_within_tolerance", "start_distance_median", "start_distance_max",
                       "start_hand_object_median", "data_start_hand_object_median", "replay_success_rate",
                       "claimed_stop_rule_mean_generated", "replayed_stop_rule_mean_generated")


def summarize_samples(samples: list[dict]) -> dict:
    """The summary fields of :func:`open_loop_improvement`'s per-sample dicts: the share starting within
    ``START_TOLERANCE`` of a dataset start, median / max start distance, median hand-object distance at the
    start (sample and data; only where the samples carry it, i.e. not in files written before it existed),
    the share of replays that succeed, and the mean claimed / replayed stop-rule return. Medians are the
    lower median (``torch.median``).

    Example:
        >>> s = [{"start_distance": 0.0, "replay_success": True, "claimed_stop_rule": 3.0, "replayed_stop_rule": 1.0}]
        >>> summarize_samples(s)["replay_success_rate"], summarize_samples([])["replay_success_rate"]
        (1.0, None)
    """
    if not samples:
        return dict.fromkeys(SAMPLE_SUMMARY_KEYS)

    def col(key: str) -> torch.Tensor:
        return torch.tensor([float(x[key]) for x in samples], dtype=torch.float64)

    dist = col("start_distance")
    out = {"start_within_tolerance": float((dist <= START_TOLERANCE).double().mean()),
           "start_distance_median": float(dist.median()), "start_distance_max": float(dist.max()),
           "replay_success_rate": float(col("replay_success").mean()),
           "claimed_stop_rule_mean_generated": float(col("claimed_stop_rule").mean()),
           "replayed_stop_rule_mean_generated": float(col("replayed_stop_rule").mean())}
    if "start_hand_object" in samples[0]:
        out.update(start_hand_object_median=float(col("start_hand_object").median()),
                   data_start_hand_object_median=float(col("data_start_hand_object").median()))
    return out


def locomotion_replays(env_name: str, trajs: TensorDictBase) -> tuple[torch.Tensor, list[dict]]:
    """Open-loop replays of locomotion trajectories (``observation``, ``action``, ``mask``; ``[N, H]``): each one's
    actions, clipped to ``[-1, 1]``, from the state of its own first observation until they run out or the env ends
    it (:func:`torchrl_ftb.envs.replay_locomotion_actions`).

    Returns:
        ``(returns float64 [N], episodes)``: the replays' plain returns and their per-step records.

    Example:
        >>> from torchrl_ftb.envs import make_locomotion_env
        >>> td = make_locomotion_env("hopper", seed=0).rollout(8)
        >>> trajs = td.select("observation", "action").unsqueeze(0)
        >>> trajs["mask"] = torch.ones(1, 8, dtype=torch.bool)
        >>> returns, _ = locomotion_replays("hopper", trajs)
        >>> abs(float(returns[0]) - float(td["next", "reward"].sum())) < 1e-3
        True
    """
    t = locomotion_paths(trajs)
    lengths = t["mask"].sum(-1).tolist()
    episodes = replay_locomotion_actions(env_name, t["observation"][:, 0],
                                         [t["action"][i, :n] for i, n in enumerate(lengths)])
    return torch.tensor([float(ep["reward"].sum()) for ep in episodes], dtype=torch.float64), episodes


def locomotion_open_loop_improvement(final: TensorDictBase, original: TensorDictBase, generated: torch.Tensor, *,
                                     env_name: str, progress: bool = False) -> dict:
    """The flow's improvement (original top-k -> final set) on locomotion, claimed per transition and replayed.

    Every trajectory of both sets (dataset ones too, so both sides are read alike; a dataset trajectory's replay
    gives back its recorded return, tested) is replayed open loop from the state rebuilt from its first
    observation (module docstring).

    Args:
        final: the final set (``observation``, ``action``, ``mask``; ``[K, H]``, unnormalised).
        original: the original top-k the flow started from.
        generated: ``bool [K]``, which final-set rows are generated (``source_step > 0``).
        env_name: the locomotion env (``hopper``, ``walker2d``, ``halfcheetah``).
        progress: a progress bar over the replays.

    Returns:
        ``num_generated``, ``horizon`` (None: plain returns only), ``improvement``
        (``{"plain": {"claimed" | "replayed": return_summary}}``), ``replay_terminated_rate`` /
        ``replay_length_fraction_median`` (generated ones: share the env ended before their actions ran out; median
        share of their steps the replay ran), ``claimed_plain_mean_generated`` / ``replayed_plain_mean_generated``
        and ``samples`` (one dict per generated trajectory: length, replay length, claimed and replayed returns,
        whether the env ended the replay early).

    Example:
        >>> from torchrl_ftb.envs import make_locomotion_env
        >>> td = make_locomotion_env("hopper", seed=0).rollout(8)
        >>> trajs = td.select("observation", "action").unsqueeze(0)
        >>> trajs["mask"] = torch.ones(1, 8, dtype=torch.bool)
        >>> out = locomotion_open_loop_improvement(trajs, trajs, torch.tensor([True]), env_name="hopper")
        >>> r = out["improvement"]["plain"]["replayed"]
        >>> abs(r["true_return_mean_after"] - float(td["next", "reward"].sum())) < 1e-3, out["replay_terminated_rate"]
        (True, 0.0)
    """
    generated, sets, claimed = locomotion_sets("locomotion_open_loop_improvement", env_name, final, original, generated)
    replayed = []
    for t in tqdm(sets, desc=f"{env_name} open-loop replays (top-k, final set)", disable=not progress):
        returns, episodes = locomotion_replays(env_name, t)  # the last pass's (the final set's) episodes are kept
        replayed.append(returns)
    lengths = sets[1]["mask"].sum(-1).tolist()
    samples = [{"length": int(lengths[i]), "replay_length": len(episodes[i]["reward"]),
                "replay_terminated": ended_early(episodes[i], lengths[i]),
                "claimed_plain": float(claimed[1][i]), "replayed_plain": float(replayed[1][i])}
               for i in generated.nonzero().squeeze(-1).tolist()]
    return {"num_generated": len(samples), "horizon": None,
            "replay_terminated_rate": samples_mean(samples, "replay_terminated"),
            "replay_length_fraction_median": (float(np.median([x["replay_length"] / max(x["length"], 1) for x in samples]))
                                              if samples else None),
            "claimed_plain_mean_generated": samples_mean(samples, "claimed_plain"),
            "replayed_plain_mean_generated": samples_mean(samples, "replayed_plain"),
            "improvement": {"plain": {"claimed": return_summary(*claimed), "replayed": return_summary(*replayed)}},
            "samples": samples}
