"""Benchmark: how faithful is the learned preference score s_psi? (paper §4.2, Fig. 3)

(a) Meta-World v3 (IPL-style data from ``torchrl_ftb.datasets``): train on 30 scripted labels
    of full trajectories (return teacher and success teacher), then Spearman/Pearson of the
    score with the true return and with success over the whole dataset, the transition-level
    correlation of r_psi with the true reward, and pairwise accuracy on fresh scripted pairs.
(b) Preference-Transformer labels for hopper-medium-expert-v2 (human and script files):
    train on ``*_train``, pairwise accuracy on ``*_eval`` of both files, and Spearman of the
    segment score with a hopper return proxy ``sum(1 + obs[5] - 1e-3 |a|^2)`` (x-velocity
    proxy; the files carry no reward).

Not a test. Usage:
    nice -n 10 python bench/score_model.py [--part a|b|ab] [--tasks ...] [--steps 300]
Writes bench/results/score_model_metaworld.json (a) and score_model_hopper.json (b) (command,
config, git commit, machine, results), rewritten after every task so partial results survive.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TASKS = ("button-press-v3", "plate-slide-v3", "drawer-open-v3", "sweep-into-v3", "assembly-v3")  # cheapest first
PT_DIR = Path("/work/shared/data/pt-human-labels/hopper-medium-expert-v2")


def _summary(values: list[float]) -> dict:
    t = torch.tensor(values, dtype=torch.float64)
    return {"mean": float(t.mean()), "std": float(t.std()) if len(values) > 1 else 0.0, "values": values}


def _train(labels, obs_dim: int, act_dim: int, args, seed: int, *, data, eval_labels=None):
    from torchrl_ftb.preference import ScoreModel, train_score_model

    model = ScoreModel(obs_dim, act_dim, num_cells=args.num_cells, num_layers=args.num_layers, seed=seed,
                       num_members=args.members, reward_activation=args.reward_activation)
    if args.normalize_obs:
        model.fit_normalizer(data)
    start = time.perf_counter()
    out = train_score_model(model, labels, steps=args.steps, batch_size=256, lr=args.lr, eval_fraction=0.0,
                            eval_labels=eval_labels, seed=seed, progress=False)
    out.pop("history")
    out["train_seconds"] = round(time.perf_counter() - start, 2)
    return model, out


def part_a(args, record: dict, write) -> None:
    from torchrl_ftb.data.labels import METAWORLD_NUM_LABELS, ReturnTeacher, SuccessTeacher, make_scripted_labels
    from torchrl_ftb.datasets import make_metaworld_dataset
    from torchrl_ftb.preference import plot_preference_scatter, preference_metrics

    results = record["results"].setdefault("metaworld", {})
    for task in args.tasks:
        start = time.perf_counter()
        trajs, meta = make_metaworld_dataset(task, episodes_per_group=args.episodes_per_group, noise=args.noise,
                                             seed=0, num_workers=args.workers, progress=False)
        trajs = trajs.select("observation", "action", "mask", ("next", "reward"), ("next", "success"),
                             ("next", "terminated"))
        data_s = time.perf_counter() - start
        true_ret = ReturnTeacher().returns(trajs)
        success = SuccessTeacher().succeeded(trajs)
        obs_dim, act_dim = trajs["observation"].shape[-1], trajs["action"].shape[-1]
        task_out = {"num_trajectories": trajs.batch_size[0], "horizon": trajs.batch_size[1],
                    "success_rate": float(success.float().mean()), "dataset_seconds": round(data_s, 1),
                    "dataset_path": meta.get("path"), "teachers": {}}
        for teacher in [t for t in (ReturnTeacher(), SuccessTeacher()) if t.base_name in args.teachers]:
            per_seed = []
            for seed in args.seeds:
                labels = make_scripted_labels(trajs, num_pairs=METAWORLD_NUM_LABELS, teacher=teacher, seed=seed)
                fresh = make_scripted_labels(trajs, num_pairs=args.eval_pairs, teacher=teacher, seed=seed + 1000)
                model, train_out = _train(labels, obs_dim, act_dim, args, seed, data=trajs)
                metrics = preference_metrics(model, trajs, true_returns=true_ret, success=success, labels=fresh)
                per_seed.append({"seed": seed, "train": train_out, "label_ties": int((labels["label"] == 0.5).sum()),
                                 **metrics})
                if seed == args.seeds[0] and args.plots:
                    plot_preference_scatter(model, trajs, Path(args.out_dir) / f"score_model-{task}-{teacher.base_name}.png",
                                            true_returns=true_ret, title=f"{task}, {teacher.name} teacher, 30 labels")
                print(f"{task} {teacher.name} seed {seed}: spearman return "
                      f"{metrics['trajectory_spearman_return']:.3f} success {metrics['trajectory_spearman_success']:.3f} "
                      f"transition {metrics['transition_spearman_reward']:.3f} acc {metrics['pairwise_accuracy']:.3f}",
                      flush=True)
            keys = ("trajectory_spearman_return", "trajectory_pearson_return", "trajectory_spearman_success",
                    "transition_spearman_reward", "transition_pearson_reward", "pairwise_accuracy")
            task_out["teachers"][teacher.name] = {
                "summary": {k: _summary([r[k] for r in per_seed]) for k in keys}, "runs": per_seed}
        results[task] = task_out
        write()


def _hopper_return_proxy(trajs) -> torch.Tensor:
    obs, act, mask = trajs["observation"], trajs["action"], trajs["mask"]
    r = 1.0 + obs[..., 5] - 1e-3 * act.pow(2).sum(-1)
    return (r * mask).sum(-1)


def part_b(args, record: dict, write) -> None:
    from torchrl_ftb.data.labels import load_pt_labels
    from torchrl_ftb.preference import correlations, pairwise_accuracy, score_trajectories

    files = {kind: {split: PT_DIR / f"num100_{kind}_{split}.npz" for split in ("train", "eval")}
             for kind in ("human", "script")}
    labels = {kind: {split: load_pt_labels(p) for split, p in d.items()} for kind, d in files.items()}
    segments = torch.cat([labels[k][s][tau].select("observation", "action", "mask")
                          for k in labels for s in ("train", "eval") for tau in ("tau0", "tau1")], 0)
    proxy = _hopper_return_proxy(segments)
    out = {"label_files": {k: {s: str(p) for s, p in d.items()} for k, d in files.items()},
           "num_segments_for_proxy": segments.batch_size[0], "by_train_file": {}}
    for kind in ("human", "script"):
        train = labels[kind]["train"]
        per_seed = []
        for seed in args.seeds:
            model, train_out = _train(train, 11, 3, args, seed, data=segments)
            row = {"seed": seed, "train": train_out,
                   "train_accuracy": pairwise_accuracy(model, train),
                   "eval_accuracy_human": pairwise_accuracy(model, labels["human"]["eval"]),
                   "eval_accuracy_script": pairwise_accuracy(model, labels["script"]["eval"]),
                   "spearman_return_proxy": correlations(score_trajectories(model, segments), proxy)["spearman"]}
            per_seed.append(row)
            print(f"hopper {kind}-trained seed {seed}: " + ", ".join(
                f"{k} {v:.3f}" for k, v in row.items() if isinstance(v, float)), flush=True)
        keys = ("train_accuracy", "eval_accuracy_human", "eval_accuracy_script", "spearman_return_proxy")
        out["by_train_file"][kind] = {
            "num_train": train.batch_size[0], "train_ties": int((train["label"] == 0.5).sum()),
            "summary": {k: _summary([r[k] for r in per_seed]) for k in keys}, "runs": per_seed}
    # how often do the labels themselves agree with the proxy (non-tie pairs)?
    agree = {}
    for kind in ("human", "script"):
        for split in ("train", "eval"):
            lab = labels[kind][split]
            decided = lab["label"] != 0.5
            p0, p1 = _hopper_return_proxy(lab["tau0"]), _hopper_return_proxy(lab["tau1"])
            agree[f"{kind}_{split}"] = float(((p1 > p0) == (lab["label"] > 0.5))[decided].float().mean())
    out["label_agreement_with_proxy"] = agree
    record["results"]["hopper_pt_labels"] = out
    write()


def main() -> None:
    from torchrl_ftb.preference import REWARD_ACTIVATIONS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", default="ba", help="a (Meta-World), b (hopper PT labels), or both ('ab'/'ba')")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--teachers", nargs="+", default=["return", "success"], help="part a: return and/or success")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--num-cells", type=int, default=256)
    parser.add_argument("--num-layers", type=int, default=3)
    parser.add_argument("--members", type=int, default=1, help="score-model ensemble size (score = member mean)")
    parser.add_argument("--reward-activation", default="identity", choices=sorted(REWARD_ACTIVATIONS),
                        help="r_psi output squashing (ScoreModel(reward_activation=...))")
    parser.add_argument("--episodes-per-group", type=int, default=25)
    parser.add_argument("--noise", type=float, default=1.0)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--eval-pairs", type=int, default=300)
    parser.add_argument("--normalize-obs", action="store_true",
                        help="fit the score model's observation normaliser on the dataset before training")
    parser.add_argument("--no-plots", dest="plots", action="store_false")
    parser.add_argument("--out-dir", default=str(ROOT / "bench" / "results"))
    parser.add_argument("--tag", default="", help="suffix of the results file (variants side by side)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    from torchrl_ftb.provenance import git_commit, machine_info, write_json

    for part in args.part:
        name = {"a": "score_model_metaworld", "b": "score_model_hopper"}[part]
        out = Path(args.out_dir) / f"{name}{'_' + args.tag if args.tag else ''}.json"
        record = {"benchmark": f"score_model/{part}", "command": " ".join([sys.executable, *sys.argv]),
                  "config": dict(vars(args)), "commit": git_commit(), "machine": machine_info(),
                  "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "results": {}}

        def write(record=record, out=out) -> None:
            record["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
            write_json(out, record)

        {"a": part_a, "b": part_b}[part](args, record, write)
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
