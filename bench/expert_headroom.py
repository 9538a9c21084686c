"""How much better than the data can a Meta-World trajectory be? The scripted expert on the data's own goals.

The improvement target of issue #5 asks the flow's final set to beat the original top-k in mean *and*
max true return. A generated trajectory is only worth its return if the simulator could produce it,
so the question is how far above the data a physically possible trajectory goes. For every episode of
a run's dataset this replays the same goal and start (the generator's ``SeedSequence([seed, group,
episode])``, checked against the recorded first observation) with the task's scripted expert,
noiseless (``--noise 0``) unless told otherwise, and compares its true return with the recorded one,
under the plain sum and the stop-rule fill to ``--horizon`` steps (the teachers' definition,
:func:`torchrl_ftb.data.labels.true_return`; the recipe's ``flow.true_return_horizon``). Both returns
are the simulator's own rewards (no oracle approximation). With the run's ``checkpoints/flow.pt`` it
also reports the original top-k: the dataset's best trajectory there against the expert's best on the
same goals (the headroom of the max), and the mean headroom.

The scripted expert is a strong controller, not an optimal one, so its returns are a reference, not
a bound. JSON to ``--out`` (command, config, commit, machine).

Usage::

    python bench/expert_headroom.py --run-dirs RUN... --out bench/results/expert_headroom.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tqdm.auto import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.analysis import match_rows  # noqa: E402
from torchrl_ftb.data.labels import true_return  # noqa: E402
from torchrl_ftb.datasets import dataset_kwargs, make_dataset  # noqa: E402
from torchrl_ftb.datasets.metaworld import GROUPS, generate_metaworld_episodes  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def returns(trajs: TensorDict, *, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(plain, filled)`` ``[N]`` true returns of ``trajs`` (``mask``, ``("next", "reward")``,
    ``("next", "terminated")``): :func:`torchrl_ftb.data.labels.true_return`, the teachers' definition,
    without and with the stop-rule fill to ``horizon`` steps."""
    return true_return(trajs).double(), true_return(trajs, horizon=horizon).double()


def replay_expert(task: str, per: dict, *, seed: int, noise: float, max_steps: int, progress: bool,
                  groups: "list[str] | tuple[str, ...]" = GROUPS) -> tuple[TensorDict, torch.Tensor, torch.Tensor]:
    """The task's scripted expert on every episode's goal and start: ``(trajectories [N, max_steps]``
    (``mask``, ``("next", "reward")``, ``("next", "terminated")``: never, a success streak truncates),
    ``success [N], first_observation [N, 39])``. ``per["group"]`` indexes ``groups`` (the dataset's
    ``meta["groups"]``)."""
    jobs = [(GROUPS.index(groups[g]), e) for g, e in zip(per["group"].tolist(), per["episode"].tolist())]
    bar = tqdm(total=len(jobs), desc=f"{task} expert replays", disable=not progress)
    eps = generate_metaworld_episodes(task, jobs, seed=seed, noise=noise, max_steps=max_steps,
                                      on_episode=lambda: bar.update(1), expert=True)
    bar.close()
    reward = torch.zeros(len(eps), max_steps, dtype=torch.float64)
    mask = torch.zeros(len(eps), max_steps, dtype=torch.bool)
    for i, ep in enumerate(eps):
        n = len(ep["reward"])
        reward[i, :n], mask[i, :n] = torch.as_tensor(ep["reward"], dtype=torch.float64), True
    success = torch.tensor([bool(ep["success"].any()) for ep in eps])
    first = torch.stack([torch.as_tensor(ep["observation"][0], dtype=torch.float32) for ep in eps])
    trajs = TensorDict({"mask": mask, "next": {"reward": reward[..., None],
                                               "terminated": torch.zeros_like(mask)[..., None]}},
                       batch_size=mask.shape)
    return trajs, success, first


def stats(x: torch.Tensor) -> dict:
    return {"mean": float(x.mean()), "max": float(x.max()), "argmax": int(x.argmax())}


def load_metaworld_run(run: Path) -> tuple:
    """``(cfg, dataset, meta)`` of an FTB run on a generated Meta-World dataset (rebuilt from the cache with
    the run's settings; ``meta`` holds the generator's seed and each episode's group and index)."""
    cfg = OmegaConf.load(run / "config.yaml")
    name = str(cfg.env.name)
    td, meta = make_dataset(name, **dataset_kwargs(name, cfg.dataset, max_episode_steps=int(cfg.env.max_episode_steps),
                                                   progress=False))
    if meta.get("domain") != "metaworld":
        raise ValueError(f"{run}: {name} is not a generated Meta-World dataset (its goals and starts are needed)")
    return cfg, td, meta


def headroom(run: Path, *, noise: float, horizon: int, progress: bool) -> dict:
    cfg, td, meta = load_metaworld_run(run)
    name = str(cfg.env.name)
    per = meta["per_trajectory"]
    mask = td.get("mask")
    data_plain, data_filled = returns(td, horizon=horizon)
    data_success = td.get(("next", "success")).squeeze(-1).any(-1)
    groups = list(meta["groups"])
    expert, esuccess, first = replay_expert(name, per, seed=int(meta["seed"]), noise=noise,
                                            max_steps=int(meta["max_steps"]), progress=progress, groups=groups)
    start_error = float((first - td.get("observation")[:, 0]).abs().max())
    if start_error > 1e-4:
        raise ValueError(f"{run}: the replayed starts differ from the recorded ones by {start_error:.2g} "
                         f"(dataset generator changed?)")
    exp_plain, exp_filled = returns(expert, horizon=horizon)
    emask = expert.get("mask")
    out = {"env": name, "seed": int(cfg.seed), "dataset": meta["path"], "start_max_abs_error": start_error,
           "groups": {}}
    for g, group in enumerate(groups):
        sel = per["group"] == g
        out["groups"][group] = {
            "dataset": {"plain": stats(data_plain[sel]), "filled": stats(data_filled[sel]),
                        "success": float(data_success[sel].double().mean()),
                        "length_mean": float(mask[sel].sum(-1).double().mean())},
            "expert": {"plain": stats(exp_plain[sel]), "filled": stats(exp_filled[sel]),
                       "success": float(esuccess[sel].double().mean()),
                       "length_mean": float(emask[sel].sum(-1).double().mean())}}
    out["all"] = {"dataset": {"plain": stats(data_plain), "filled": stats(data_filled)},
                  "expert": {"plain": stats(exp_plain), "filled": stats(exp_filled)}}
    flow_ckpt = run / "checkpoints" / "flow.pt"
    if flow_ckpt.exists():
        ckpt = torch.load(flow_ckpt, map_location="cpu", weights_only=True)
        rows = match_rows(ckpt["original"]["data"]["observation"].float(), td.get("observation"))
        top = {}
        for ret, (d, e) in (("plain", (data_plain, exp_plain)), ("filled", (data_filled, exp_filled))):
            d, e = d[rows], e[rows]
            top[ret] = {"dataset": stats(d), "expert": stats(e),
                        "max_headroom": float(e.max() - d.max()),
                        "max_headroom_fraction": float((e.max() - d.max()) / d.max().abs()),
                        "per_goal_gain_mean": float((e - d).mean()),
                        "per_goal_expert_better": float((e > d).double().mean())}
        out["top_k"] = {"k": int(rows.numel()), "groups": {g: int((per["group"][rows] == i).sum())
                                                           for i, g in enumerate(groups)}, **top}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dirs", nargs="+", type=Path, required=True,
                        help="FTB run directories of recipes/ftb_offline.py on generated Meta-World data")
    parser.add_argument("--noise", type=float, default=0.0, help="the expert's action noise (default: none)")
    parser.add_argument("--horizon", type=int, default=500, help="stop-rule fill horizon of the filled return")
    parser.add_argument("--out", type=Path, default=ROOT / "bench/results/expert_headroom.json")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args()
    runs = {str(r): headroom(r, noise=args.noise, horizon=args.horizon, progress=not args.no_progress)
            for r in args.run_dirs}
    for r in runs.values():
        t = r.get("top_k", {})
        line = "  ".join(f"{ret}: top-k max {t[ret]['dataset']['max']:.0f} vs expert {t[ret]['expert']['max']:.0f}, "
                         f"mean {t[ret]['dataset']['mean']:.0f} vs {t[ret]['expert']['mean']:.0f}"
                         for ret in ("plain", "filled") if ret in t)
        print(f"{r['env']} seed {r['seed']}: {line}")
    write_json(args.out, {**run_record(config={"run_dirs": [str(r) for r in args.run_dirs], "noise": args.noise,
                                               "horizon": args.horizon}), "runs": runs})


if __name__ == "__main__":
    main()
