"""Benchmark: does choosing *which* 30 pairs to label lift s_psi's ranking? (issue #3, exploratory)

``bench/score_groups.py`` found that 30 uniformly drawn full-trajectory pairs mostly teach the
order of the dataset's behaviour groups, rarely the order inside them. Active query selection is
the PbRL answer (PEBBLE, Lee et al. 2021; OPRL, Shin et al. 2023): label a few random pairs, then
ask the teacher about the pairs the current model is least sure of. Strategies (same 30-label
budget, same teacher, same final model):

* ``random``       -- 30 uniform pairs (the recipe's labels, ``make_scripted_labels``);
* ``disagreement`` -- ``--initial`` uniform pairs, then rounds of ``--per-round`` pairs with the
  largest std over a ``--members``-member ensemble of ``P(tau1 > tau0)`` among all pairs of the
  dataset (the ensemble retrained on every round's labels), no trajectory in two pairs of a round
  (``--no-distinct``: pure top-k);
* ``entropy``      -- the same rounds with one model: the pairs whose ``P(tau1 > tau0)`` is
  closest to 0.5.

The final score model is the recipe's ``cpu``-preset s_psi (normalised r_psi, 256x3, 500
full-batch Adam steps at lr 1e-3), built and trained by the recipe's own ``make_score_model`` /
``fit_score_model`` on the 30 chosen labels, so only the choice of pairs differs
(``--reward-activation``, ``--steps``, ``--lr``, ``--final-members`` change that model, the first also
the provisional ones). The strategies are the library's ``torchrl_ftb.preference.make_query_labels`` (the
recipes' ``labels.query``). Reports Spearman(s_psi, true return) over the whole dataset per label seed, and
beside it Spearman(s_psi, success), the share of successes among the s_psi top-100 (the set FTB's flow starts
from) and the mean length of the top 25. ``--teacher success`` labels with the success-aware teacher,
``--teacher-horizon`` / ``--score-horizon`` set the stop-rule fill of the teacher (``labels.horizon``) / of
s_psi (``score_model.horizon``); the Spearman stays with the plain true return. Not a test.

    python bench/score_model_queries.py --task button-press-v3 --strategies random disagreement entropy
    python bench/score_model_queries.py --summary     # the Markdown table of the committed results
    python bench/score_model_queries.py --pooled bench/results bench/results/score_model_queries_seeds5-9 \
        bench/results/score_model_queries_seeds5-9_random   # label seeds 0-9 pooled, with standard errors

Writes bench/results/score_model_queries_<task>.json (command, config, commit, machine,
results), rewritten after every strategy; results already in the file for other keys are kept (each
result records the command, commit and machine that made it).

    python bench/score_model_queries.py --task plate-slide-v3 --strategies disagreement --final-members 1 3
    python bench/score_model_queries.py --task drawer-open-v3 --strategies disagreement --reward-activation sigmoid
    python bench/score_model_queries.py --task drawer-open-v3 --strategies disagreement --seeds 5 6 7 8 9 \
        --out-dir bench/results/score_model_queries_seeds5-9   # held-out label seeds
    python bench/score_model_queries.py --task plate-slide-v3 --strategies random --teacher success \
        --score-horizon 500 --out-dir bench/results/score_model_queries_success   # success teacher, filled s_psi
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDictBase

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


@functools.cache
def _recipe():
    """The FTB recipe module and its config file, loaded once per process (not for ``--summary``)."""
    from omegaconf import OmegaConf

    from torchrl_ftb.testing import load_script

    return (load_script(ROOT / "recipes" / "ftb_offline.py", "ftb_offline_recipe"),
            OmegaConf.load(ROOT / "recipes" / "config" / "ftb_offline.yaml"))


def final_scores(trajs: TensorDictBase, labels: TensorDictBase, *, seed: int, steps: int, lr: float,
                 members: int = 1, reward_activation: str = "identity", horizon: int | None = None) -> torch.Tensor:
    """Scores ``[N]`` of the recipe's score model trained on ``labels`` by the recipe's own
    ``make_score_model`` / ``fit_score_model`` (its config with ``seed``, ``score_model.steps``, ``.lr``,
    ``.num_members``, ``.reward_activation`` and ``.horizon`` set)."""
    from omegaconf import OmegaConf

    from torchrl_ftb.preference import score_trajectories

    recipe, base_cfg = _recipe()
    cfg = OmegaConf.merge(base_cfg, {
        "seed": seed, "progress": False,
        "score_model": {"steps": steps, "lr": lr, "num_members": members, "reward_activation": reward_activation,
                        "horizon": horizon}})
    pool = trajs.select("observation", "action", "mask")
    model = recipe.make_score_model(cfg, pool["observation"].shape[-1], pool["action"].shape[-1], "cpu")
    recipe.fit_score_model(cfg, model, pool, labels.select("tau0", "tau1", "label"), "cpu")
    return score_trajectories(model, pool)


def result_key(strategy: str, final_members: int, *, per_round: int = 10, steps: int = 500,
               lr: float = 1e-3, reward_activation: str = "identity", horizon: int | None = None,
               teacher: str = "return") -> str:
    """``"disagreement"`` for the recipe's ``cpu``-preset one-member s_psi (500 steps at lr 1e-3) and rounds
    of 10, ``"disagreement+ens3"`` for a 3-member final s_psi, ``"disagreement-r5"`` for rounds of 5 pairs
    (``random`` has no rounds), ``"disagreement@s1500-lr0.0001"`` for a final s_psi trained otherwise
    (here the ``paper`` preset's), ``"disagreement+sigmoid"`` for ``score_model.reward_activation=sigmoid``
    (provisional and final models), ``"random+h500"`` for ``score_model.horizon=500`` (the stop-rule fill),
    ``"success:random"`` for another teacher than the paper's ``return`` (its name, e.g.
    ``return(horizon=500)``, before the colon)."""
    key = strategy if per_round == 10 or strategy == "random" else f"{strategy}-r{per_round}"
    if (steps, lr) != (500, 1e-3):
        key = f"{key}@s{steps}-lr{lr:g}"
    if reward_activation != "identity":
        key = f"{key}+{reward_activation}"
    if horizon is not None:
        key = f"{key}+h{horizon}"
    key = key if final_members == 1 else f"{key}+ens{final_members}"
    return key if teacher == "return" else f"{teacher}:{key}"


def earlier_results(path: Path) -> dict:
    """The results already in ``path`` (``{}`` if none), each stamped with the command, commit and
    machine of the file that holds it if it does not carry its own (files written before results
    were merged), so a later run that rewrites the file's top level keeps their provenance."""
    if not path.exists():
        return {}
    record = json.loads(path.read_text())
    results = record["results"]
    for res in results.values():
        for field in ("command", "commit", "machine"):
            res.setdefault(field, record.get(field))
    return results


def summary(results_dir: Path) -> str:
    """Markdown table of every ``score_model_queries_<task>.json`` in ``results_dir``, a column per
    result key found (a ``random`` missing there is taken from ``score_model_queries_nodistinct/``,
    marked ``*``: ``random`` has no rounds, so it is the same there)."""
    def cell(res: dict | None, mark: str = "") -> str:
        if res is None:
            return "—"
        seeds = " / ".join(f"{v:.2f}" for v in res["spearman_return"])
        mean = f"{res['mean']:.4f}"  # 4 decimals: 0.7999 is not 0.800
        return f"**{mean}**{mark} ({seeds})" if res["mean"] >= 0.8 else f"{mean}{mark} ({seeds})"

    paths = sorted(results_dir.glob("score_model_queries_*.json"))
    files = {path: json.loads(path.read_text())["results"] for path in paths}
    keys = ["random", "entropy", "disagreement"]
    keys += sorted({key for results in files.values() for key in results} - set(keys))
    rows = ["| task | " + " | ".join(k + " (the paper)" if k == "random" else k for k in keys) + " |",
            "|---" * (len(keys) + 1) + "|"]
    for path, results in files.items():
        task = path.stem.removeprefix("score_model_queries_")
        old = results_dir / "score_model_queries_nodistinct" / path.name
        old_results = json.loads(old.read_text())["results"] if old.exists() else {}
        row = []
        for key in keys:
            if key in results:
                row.append(cell(results[key]))
            else:
                row.append(cell(old_results.get(key) if key == "random" else None, "*"))
        rows.append(f"| {task} | " + " | ".join(row) + " |")
    return "\n".join(rows)


def pooled(results_dirs: list[Path], keys: list[str] | None = None, metric: str = "spearman_return") -> str:
    """Markdown table: per task and result key, Spearman pooled over every label seed found in
    ``results_dirs`` (e.g. seeds 0-4 in ``bench/results`` and held-out seeds 5-9 elsewhere), as
    mean +- standard error of the mean, the seed count, and the per-directory means. A seed that
    appears twice for one key is an error (two directories made with the same seeds). ``keys``: only
    these result keys (default: all). Results made before seeds were recorded ran seeds ``0..n-1``.
    ``metric``: a per-seed list of the results (``spearman_return``, or ``spearman_success``,
    ``top100_success``, ``top25_length`` where recorded; results without it are left out)."""
    table: dict[tuple[str, str], dict[int, float]] = {}
    parts: dict[tuple[str, str], list[str]] = {}
    for results_dir in results_dirs:
        for path in sorted(results_dir.glob("score_model_queries_*.json")):
            task = path.stem.removeprefix("score_model_queries_")
            for key, res in json.loads(path.read_text())["results"].items():
                if (keys is not None and key not in keys) or metric not in res:
                    continue
                res.setdefault("seeds", list(range(len(res["spearman_return"]))))
                seeds = table.setdefault((task, key), {})
                values = res[metric]
                for seed, value in zip(res["seeds"], values):
                    if seed in seeds:
                        raise ValueError(f"{path}: {key!r} label seed {seed} also in another directory")
                    seeds[seed] = value
                parts.setdefault((task, key), []).append(
                    f"{sum(values) / len(values):.3f} (seeds {min(res['seeds'])}-{max(res['seeds'])})")
    rows = [f"| task | result | seeds | pooled {metric} (mean ± s.e.) | per directory |", "|---|---|---|---|---|"]
    for (task, key), seeds in sorted(table.items()):
        vals = torch.tensor(list(seeds.values()), dtype=torch.float64)
        se = (vals.std() / len(vals) ** 0.5).item() if len(vals) > 1 else float("nan")
        rows.append(f"| {task} | {key} | {len(vals)} | {vals.mean().item():.3f} ± {se:.3f} | "
                    + " / ".join(parts[(task, key)]) + " |")
    return "\n".join(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="button-press-v3")
    parser.add_argument("--strategies", nargs="+", default=["random", "disagreement", "entropy"],
                        choices=["random", "disagreement", "entropy"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--num-labels", type=int, default=30)
    parser.add_argument("--initial", type=int, default=10)
    parser.add_argument("--per-round", type=int, default=10)
    parser.add_argument("--members", type=int, default=3)
    parser.add_argument("--round-steps", type=int, default=300)
    parser.add_argument("--no-distinct", dest="distinct", action="store_false",
                        help="let one trajectory appear in several pairs of a round (pure top-k; the "
                             "score_model_queries_nodistinct/ results, made before the option existed)")
    parser.add_argument("--final-members", nargs="+", type=int, default=[1],
                        help="ensemble sizes of the final s_psi, each trained on the same label sets "
                             "(1: the recipe's default; 3: score_model.num_members=3); results key "
                             "'<strategy>' for 1, '<strategy>+ens<m>' otherwise ('-r<n>' after the strategy when "
                             "--per-round is not 10)")
    parser.add_argument("--steps", type=int, default=500, help="final s_psi: full-batch Adam steps "
                        "(500: the recipe's cpu preset, 1500: its paper preset)")
    parser.add_argument("--lr", type=float, default=1e-3, help="final s_psi: Adam lr (1e-3 cpu, 1e-4 paper)")
    parser.add_argument("--round-lr", type=float, default=1e-3,
                        help="provisional models of the query rounds: Adam lr (the recipe's labels.query.lr)")
    parser.add_argument("--reward-activation", default="identity", choices=["identity", "sigmoid"],
                        help="score_model.reward_activation of the provisional and the final models")
    parser.add_argument("--teacher", default="return", choices=["return", "success"],
                        help="scripted teacher of the labels (the Spearman is always with the plain true return)")
    parser.add_argument("--teacher-horizon", type=int, default=None,
                        help="the teacher's stop-rule fill (labels.horizon; default: the paper's plain sum)")
    parser.add_argument("--score-horizon", type=int, default=None,
                        help="s_psi's stop-rule fill (score_model.horizon), provisional and final models")
    parser.add_argument("--out-dir", default=str(ROOT / "bench" / "results"))
    parser.add_argument("--summary", action="store_true", help="print the Markdown table of --out-dir and exit")
    parser.add_argument("--pooled", nargs="+", default=None, metavar="DIR",
                        help="print Spearman pooled over the label seeds of these results directories and exit")
    parser.add_argument("--keys", nargs="+", default=None, help="with --pooled: only these result keys")
    parser.add_argument("--metric", default="spearman_return",
                        choices=["spearman_return", "spearman_success", "top100_success", "top25_length"],
                        help="with --pooled: the per-seed value to pool")
    args = parser.parse_args()
    if args.pooled:
        print(pooled([Path(d) for d in args.pooled], args.keys, args.metric))
        return
    if args.summary:
        print(summary(Path(args.out_dir)))
        return
    torch.set_num_threads(1)
    from torchrl_ftb.data import trajectory_lengths
    from torchrl_ftb.data.labels import ReturnTeacher, SuccessTeacher, make_teacher
    from torchrl_ftb.datasets import make_metaworld_dataset
    from torchrl_ftb.preference import correlations, make_query_labels, top_k_mean
    from torchrl_ftb.provenance import git_commit, machine_info, write_json

    trajs, meta = make_metaworld_dataset(args.task, episodes_per_group=100, noise=1.0, seed=0, progress=False)
    teacher = make_teacher(args.teacher, horizon=args.teacher_horizon)
    returns = ReturnTeacher().returns(trajs)  # the metric: the plain true return, whatever the teacher
    success, lengths = SuccessTeacher().succeeded(trajs).float(), trajectory_lengths(trajs).float()
    group = torch.as_tensor(meta["per_trajectory"]["group"])  # expert / within-env / random / cross-env
    out = Path(args.out_dir) / f"score_model_queries_{args.task}.json"
    command = " ".join([sys.executable, *sys.argv])
    # merged into the file: each result keeps the command, commit and machine that made it
    results = earlier_results(out)
    record = {"benchmark": "score_model_queries", "command": command, "config": dict(vars(args)),
              "commit": git_commit(), "machine": machine_info(), "dataset_path": meta.get("path"),
              "teacher": teacher.name, "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "results": results}
    key_options = {"per_round": args.per_round, "steps": args.steps, "lr": args.lr,
                   "reward_activation": args.reward_activation, "horizon": args.score_horizon,
                   "teacher": teacher.name}
    for strategy in args.strategies:
        start, within = time.perf_counter(), []
        values = {m: [] for m in args.final_members}
        extra = {m: {"spearman_success": [], "top100_success": [], "top25_length": []} for m in args.final_members}
        for seed in args.seeds:
            labels = make_query_labels(trajs, num_pairs=args.num_labels, teacher=teacher, seed=seed,
                                       strategy=strategy, initial=args.initial, per_round=args.per_round,
                                       members=args.members, distinct=args.distinct, steps=args.round_steps,
                                       lr=args.round_lr,
                                       model_kwargs={"reward_activation": args.reward_activation,
                                                     "horizon": args.score_horizon})
            same = (group[labels["index0"]] == group[labels["index1"]]).sum().item()
            within.append(int(same))
            for m in args.final_members:
                scores = final_scores(trajs, labels, seed=seed, steps=args.steps, lr=args.lr, members=m,
                                      reward_activation=args.reward_activation, horizon=args.score_horizon)
                values[m].append(round(correlations(scores, returns)["spearman"], 4))
                extra[m]["spearman_success"].append(round(correlations(scores, success)["spearman"], 4))
                extra[m]["top100_success"].append(round(top_k_mean(scores, success, 100), 4))
                extra[m]["top25_length"].append(round(top_k_mean(scores, lengths, 25), 1))
                print(f"{args.task} {result_key(strategy, m, **key_options)} seed {seed}: {values[m][-1]} "
                      f"(success {extra[m]['spearman_success'][-1]}, top-100 successes "
                      f"{extra[m]['top100_success'][-1]}, top-25 length {extra[m]['top25_length'][-1]}; "
                      f"{same} within-group pairs)", flush=True)
        for m, vals in values.items():
            mean = sum(vals) / len(vals)
            results[result_key(strategy, m, **key_options)] = {
                "spearman_return": vals, **extra[m], "teacher": teacher.name, "score_horizon": args.score_horizon,
                "seeds": list(args.seeds), "mean": round(mean, 4), "within_group_pairs": within,
                "final_members": m, "per_round": args.per_round, "final_steps": args.steps, "final_lr": args.lr, "reward_activation": args.reward_activation, "seconds": round(time.perf_counter() - start, 1), "command": command,
                "commit": record["commit"], "machine": record["machine"]}
            print(f"{args.task} {result_key(strategy, m, **key_options)}: {vals} mean {mean:.3f}", flush=True)
        record["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
        write_json(out, record)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
