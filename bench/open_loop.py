"""Do a run's generated trajectories do in the simulator what their states say? Open-loop replays.

The flow's "true return" of a generated Meta-World trajectory is the task's reward read off the
*generated* observations (:func:`torchrl_ftb.envs.true_reward_fn`); the physics proxies
(``bench/flow_generated.py``) only ask whether those observations look physical. This bench asks the
simulator directly. For every generated trajectory in an FTB run's final set (``checkpoints/flow.pt``)
it finds the dataset episode it starts from (the nearest first observation; a sample edits or is
conditioned on a trajectory that starts there), replays the sample's actions open loop from that
episode's own goal and start (:func:`torchrl_ftb.datasets.metaworld.replay_metaworld_actions`: the
same reset as the data, the data's stop rule; after the sample's last action the hand holds still,
zero actions, until the stop rule or the time limit, as an episode runs on -- ``--no-hold`` stops
there instead), and compares the simulator's return with the one its states claim. Replaying a recorded episode's own actions reproduces it (tested), so a gap is the
sample's.

Returns are the stop-rule return of the flow's statistics (``--horizon`` steps, after a
``SUCCESS_STREAK`` cut; a trajectory that no stop rule ended earns its own steps only) and the plain
sum. Reported per run, original top-k -> final set: "claimed", every return read off the states as the
flow computes them; "replayed", the simulator's own (recorded rewards for dataset trajectories, the
replay for generated ones: what their actions achieve) -- the improvement target measured in the
simulator. Read off recorded states, a return is exact up to the rewarder's approximations (about 1 %). Open-loop replay is the
strictest reading: a policy cloned from the sample would act in closed loop.

Usage::

    python bench/open_loop.py --run-dirs RUN [RUN ...] --horizon 500 --out bench/results/open_loop.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from expert_headroom import load_metaworld_run, match_rows  # noqa: E402
from flow_generated import metaworld_returns, require_finished_runs  # noqa: E402

from torchrl_ftb.data import stop_rule_fill  # noqa: E402
from torchrl_ftb.data.labels import true_return  # noqa: E402
from torchrl_ftb.datasets.metaworld import GROUPS, SUCCESS_STREAK, replay_metaworld_actions  # noqa: E402
from torchrl_ftb.flow import clip_actions, return_summary  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def replay_returns(episodes: list[dict], *, horizon: int) -> torch.Tensor:
    """``float64 [N, 2]``: plain sum and stop-rule return (filled to ``horizon`` only where the stop rule
    ended the replay) of open-loop replays."""
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


def nearest_start(first: torch.Tensor, data_first: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Dataset row whose first observation is nearest to each sample's, and the distance (max-abs)."""
    dist = (first[:, None] - data_first[None]).abs().amax(-1)
    best = dist.min(-1)
    return best.indices, best.values


def open_loop(run: Path, *, horizon: int, progress: bool, hold: bool = True) -> dict:
    cfg, data, meta = load_metaworld_run(run)
    task = str(cfg.env.name)
    ckpt = torch.load(run / "checkpoints" / "flow.pt", weights_only=True)
    final = TensorDict(ckpt["trajectories"]["data"], batch_size=ckpt["trajectories"]["batch_size"])
    original = TensorDict(ckpt["original"]["data"], batch_size=ckpt["original"]["batch_size"])
    generated = ckpt["source_step"] > 0
    # claimed: the returns as the flow computes them, read off the states (for recorded states too: exact up
    # to the rewarder's approximations, e.g. the last step's next observation, about 1 % on a return)
    state_read = metaworld_returns(task, clip_actions(original.select("observation", "action", "mask").clone(), 1.0),
                                   horizon=horizon)
    claimed = metaworld_returns(task, clip_actions(final.select("observation", "action", "mask").clone(), 1.0),
                                horizon=horizon)
    # in the simulator: recorded rewards for dataset trajectories (the original top-k, the final set's
    # originals; rows checked to be the dataset's), open-loop replays for generated ones
    recorded = torch.stack([true_return(data).double(), true_return(data, horizon=horizon).double()], -1)
    sim_before = recorded[match_rows(original["observation"].float(), data["observation"])]
    gen = final[generated]
    start_row, start_dist = nearest_start(gen["observation"][:, 0].float(), data["observation"][:, 0])
    per, groups = meta["per_trajectory"], list(meta["groups"])
    jobs = [(GROUPS.index(groups[int(per["group"][r])]), int(per["episode"][r])) for r in start_row.tolist()]
    lengths = gen["mask"].sum(-1).tolist()
    limit = int(meta["max_steps"])
    actions = [gen["action"][i, :n].numpy() for i, n in enumerate(lengths)]
    if hold:  # after its last action the hand holds still, as an episode runs on until the stop rule or the limit
        actions = [np.concatenate([a, np.zeros((limit - len(a), a.shape[-1]), dtype=a.dtype)]) for a in actions]
    bar = tqdm(total=len(jobs), desc=f"{task} open-loop replays", disable=not progress)
    episodes = replay_metaworld_actions(task, jobs, actions, seed=int(meta["seed"]),
                                        max_steps=limit, on_episode=lambda: bar.update(1))
    bar.close()
    replayed = replay_returns(episodes, horizon=horizon)
    real = torch.zeros(final.batch_size[0], 2, dtype=torch.float64)  # plain, stop-rule
    real[generated] = replayed
    if bool((~generated).any()):
        real[~generated] = recorded[match_rows(final[~generated]["observation"].float(), data["observation"])]
    samples = [{"length": int(n), "replay_length": len(ep["reward"]), "start_row": int(r), "start_distance": float(d),
                "claimed_plain": float(c[0]), "claimed_stop_rule": float(c[2]), "replayed_plain": float(p[0]),
                "replayed_stop_rule": float(p[1]), "replay_success": bool(ep["success"].any())}
               for n, ep, r, d, c, p in zip(lengths, episodes, start_row.tolist(), start_dist.tolist(),
                                            claimed[generated], replayed)]
    out = {"env": task, "seed": int(cfg.seed), "top_k": int(original.batch_size[0]),
           "flow_filter": str(cfg.flow.get("filter", "score_model")),
           "diffuser_strength": float(cfg.diffuser.get("strength", 1.0)),
           "hold_after_last_action": hold, "num_generated": int(generated.sum()), "start_distance_max": float(start_dist.max()) if samples else None,
           "samples": samples, "improvement": {}}
    for j, name in ((0, "plain"), (1, f"stop_rule_{horizon}")):
        claim_col = 0 if j == 0 else 2
        out["improvement"][name] = {
            "claimed": return_summary(state_read[:, claim_col], claimed[:, claim_col]),
            "replayed": return_summary(sim_before[:, j], real[:, j]),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True)
    parser.add_argument("--horizon", type=int, default=500, help="the stop-rule return's horizon (Meta-World: 500)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "open_loop.json")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-hold", action="store_true",
                        help="stop each replay after the sample's last action (default: the hand then holds still, "
                             "zero actions, until the stop rule or the time limit)")
    args = parser.parse_args()
    require_finished_runs(parser, args.run_dirs)
    record = {**run_record(config={"run_dirs": [str(r) for r in args.run_dirs], "horizon": args.horizon,
                                   "hold": not args.no_hold}), "runs": {}}
    for run in args.run_dirs:
        entry = record["runs"][str(run)] = open_loop(run, horizon=args.horizon, progress=not args.no_progress,
                                                     hold=not args.no_hold)
        for name, v in entry["improvement"].items():
            c, r = v["claimed"], v["replayed"]
            print(f"{entry['env']} seed {entry['seed']} {name}: mean {c['true_return_mean_before']:.0f} -> "
                  f"{c['true_return_mean_after']:.0f} claimed / {r['true_return_mean_after']:.0f} replayed; max "
                  f"{c['true_return_max_before']:.0f} -> {c['true_return_max_after']:.0f} claimed / "
                  f"{r['true_return_max_after']:.0f} replayed")
        write_json(args.out, record)
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
