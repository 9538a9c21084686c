"""Table-1 harness: methods x tasks x seeds, one resumable cell at a time, and its Markdown table.

Run cells (each cell a subprocess of the recipe; a cell whose JSON exists is skipped):

    python bench/table1.py --methods bc10,td3bc,iql,iql_rpsi,oprl,ftb \\
        --tasks button-press-v3,drawer-open-v3 --seeds 0,1,2 --preset cpu --teacher return

Write the table into BENCHMARKS.md between ``<!-- table1:start -->`` and ``<!-- table1:end -->``
(``--section NAME``: between ``<!-- NAME:start -->`` and ``<!-- NAME:end -->``, e.g. for a second
results directory):

    python bench/table1.py --write-md
    python bench/table1.py --write-md --results-dir bench/results/table1_v2 --section table1-v2

Turn a finished run of the recipe made outside the harness into a cell (its metrics JSON names
the task, seed and teacher; the cell records ``imported_from`` and the run's own command):

    python bench/table1.py --import-run outputs/exp/drawer-v2 --results-dir bench/results/table1_v2

Compare one method under several configurations (one results directory each) task by task, with
the per-seed scores (printed, not written):

    python bench/table1.py --methods ftb --teacher success \
        --compare uniform=bench/results/table1_v2 disagreement=bench/results/table1_v2_active

Each cell writes ``bench/results/table1/<method>__<task>__<teacher>__seed<k>.json`` with the
command, config (overrides + the run's resolved config), git commit, machine, wall time and
score (Meta-World: success rate; locomotion: D4RL-normalised score; toy: mean return).
Baselines run ``recipes/baselines.py``; the ``ftb`` cells run ``recipes/ftb_offline.py`` with
the same task / seed / teacher / preset and read the metrics JSON of its run directory.
Run directories go under ``--runs-dir`` (default ``outputs/table1``), so a cell killed
mid-training resumes from the recipe's own checkpoints when re-run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterable

from torchrl_ftb.provenance import git_commit, machine_info, write_json

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "bench" / "results" / "table1"


def markers(section: str = "table1") -> tuple[str, str]:
    """The HTML comments that delimit a generated section of BENCHMARKS.md."""
    return f"<!-- {section}:start -->", f"<!-- {section}:end -->"

#: column order and display names (the paper's names where it has the method)
METHOD_NAMES = {
    "bc": "BC",
    "bc10": "10%BC",
    "bc10_score": "10%BC (by s_ψ)",
    "td3bc": "TD3+BC",
    "iql": "IQL",
    "iql_rpsi": "IQL+r_ψ",
    "oprl": "OPRL",
    "iql_zero": "IQL (r=0)",
    "ftb": "FTB",
}
#: Paper, Table 1 (scripted teacher; 5 seeds; their offline-RL numbers are CORL's, on D4RL v2 /
#: IPL's Meta-World v2 files). Keys are the paper's task names.
PAPER_TABLE1 = {
    "halfcheetah-medium-replay-v2": {"bc10": 23.6, "td3bc": 48.1, "iql": 48.3, "iql_rpsi": 36.0, "oprl": 38.3, "ftb": "38.4±1.3"},
    "halfcheetah-medium-expert-v2": {"bc10": 90.1, "td3bc": 90.8, "iql": 94.7, "iql_rpsi": 85.6, "oprl": 82.9, "ftb": "85.2±0.7"},
    "hopper-medium-replay-v2": {"bc10": 70.4, "td3bc": 64.4, "iql": 97.4, "iql_rpsi": 20.8, "oprl": 86.2, "ftb": "89.6±4.9"},
    "hopper-medium-expert-v2": {"bc10": 111.2, "td3bc": 101.2, "iql": 107.4, "iql_rpsi": 88.5, "oprl": 95.7, "ftb": "111.1±2.0"},
    "walker2d-medium-replay-v2": {"bc10": 54.4, "td3bc": 85.6, "iql": 82.2, "iql_rpsi": 75.7, "oprl": 64.0, "ftb": "79.1±1.4"},
    "walker2d-medium-expert-v2": {"bc10": 108.7, "td3bc": 110.0, "iql": 111.7, "iql_rpsi": 110.0, "oprl": 109.6, "ftb": "109.3±0.3"},
    "assembly-v2": {"bc10": 0.02, "td3bc": 0.00, "iql": 0.17, "iql_rpsi": 0.00, "oprl": 0.00, "ftb": "0.02±0.00"},
    "button-press-v2": {"bc10": 0.70, "td3bc": 0.61, "iql": 0.70, "iql_rpsi": 0.23, "oprl": 0.57, "ftb": "1.00±0.00"},
    "drawer-open-v2": {"bc10": 0.77, "td3bc": 1.00, "iql": 1.00, "iql_rpsi": 0.26, "oprl": 0.63, "ftb": "1.00±0.00"},
    "plate-slide-v2": {"bc10": 0.43, "td3bc": 0.58, "iql": 0.62, "iql_rpsi": 0.00, "oprl": 0.44, "ftb": "0.51±0.08"},
    "sweep-into-v2": {"bc10": 0.07, "td3bc": 0.63, "iql": 0.57, "iql_rpsi": 0.00, "oprl": 0.21, "ftb": "0.97±0.02"},
}


# ====================================================================
# Cells
# -----


def paper_task(task: str) -> str | None:
    """The paper's name of one of our tasks (``button-press-v3`` → ``button-press-v2``)."""
    candidates = [re.sub(r"-v\d+$", "", task) + "-v2", task]
    return next((c for c in candidates if c in PAPER_TABLE1), None)


def task_overrides(task: str) -> list[str]:
    """Hydra overrides selecting ``task`` (``hopper-medium-replay`` → env + dataset kind)."""
    loco = re.fullmatch(r"(hopper|walker2d|halfcheetah)-(medium-replay|medium-expert|medium)(-v\d+)?", task)
    if loco:  # dataset <env>-<kind>: torchrl_ftb.datasets.make_dataset(env, kind=...) via dataset.options
        return [f"env.name={loco.group(1)}", f"+dataset.options.kind={loco.group(2)}"]
    return [f"env.name={task}"]


def cell_path(results_dir: Path, method: str, task: str, teacher: str, seed: int) -> Path:
    return results_dir / f"{method}__{task}__{teacher}__seed{seed}.json"


def write_cell_json(path: Path, record: dict[str, Any]) -> None:
    """Write a cell's JSON atomically (temp file + ``os.replace``)."""
    write_json(path, record)


def _score_from_metrics(metrics: dict[str, Any]) -> tuple[str, float]:
    """``(name, value)`` of the headline score in a recipe's metrics JSON."""
    if "score" in metrics and isinstance(metrics["score"], (int, float)):
        return metrics.get("score_name", "score"), float(metrics["score"])
    evaluation = metrics.get("eval", metrics.get("evaluation", metrics))
    for name in ("success_rate", "normalized_score", "return_mean"):
        if isinstance(evaluation, dict) and isinstance(evaluation.get(name), (int, float)):
            return name, float(evaluation[name])
    raise ValueError(f"no score (score / success_rate / normalized_score / return_mean) in metrics: {sorted(metrics)}")


def _find_metrics(run_dir: Path) -> Path:
    for name in ("metrics.json", "final_metrics.json", "results.json"):
        if (run_dir / name).exists():
            return run_dir / name
    found = sorted(run_dir.rglob("metrics*.json"))
    if not found:
        raise FileNotFoundError(f"{run_dir}: the recipe wrote no metrics JSON")
    return found[-1]


def _task_of(env: str, config_file: Path) -> str:
    """The harness's task name of a run: ``env``, or ``<env>-<kind>`` for a locomotion dataset kind (the inverse of
    :func:`task_overrides`), read off the run's resolved ``config.yaml``."""
    if not config_file.exists():
        return env
    from omegaconf import OmegaConf  # hydra's; only the import needs it

    kind = OmegaConf.select(OmegaConf.load(config_file), "dataset.options.kind")
    return f"{env}-{kind}" if kind else env


def import_run(run_dir: Path, *, results_dir: Path, overwrite: bool = False) -> dict[str, Any]:
    """Write the cell JSON of a finished recipe run that was not started by this harness.

    The cell's method, task, seed, teacher and preset come from the run's metrics JSON (both
    recipes record them; ``recipes/ftb_offline.py`` runs are ``ftb``; a locomotion dataset kind from its
    ``config.yaml``, so the cell is named as the harness names it, e.g. ``hopper-medium-replay``); ``command``,
    ``git_commit``, ``machine`` and ``wall_time_s`` are the run's own, and ``imported_from``
    names the run directory.

    Raises:
        ValueError: the metrics JSON lacks one of those fields or a score (an unfinished run),
            or the cell exists and ``overwrite`` is False.
        FileNotFoundError: ``run_dir`` has no metrics JSON.
    """
    run_dir = Path(run_dir)
    metrics_file = _find_metrics(run_dir)
    metrics = json.loads(metrics_file.read_text())
    teacher = metrics.get("teacher", (metrics.get("labels") or {}).get("teacher"))
    missing = [k for k in ("env", "seed", "preset", "command", "wall_time_s") if k not in metrics]
    if missing or teacher is None:
        raise ValueError(f"{metrics_file}: cannot import, the metrics JSON lacks "
                         f"{missing + ([] if teacher is not None else ['teacher'])}")
    score_name, score = _score_from_metrics(metrics)
    method = str(metrics.get("method", "ftb"))
    config_file = run_dir / "config.yaml"
    task, seed, teacher = _task_of(str(metrics["env"]), config_file), int(metrics["seed"]), str(teacher).split("(")[0]
    out = cell_path(results_dir, method, task, teacher, seed)
    if out.exists() and not overwrite:
        raise ValueError(f"{out}: the cell exists; not overwritten")
    record = {
        "method": method, "env": task, "seed": seed, "teacher": teacher, "preset": str(metrics["preset"]),
        "score_name": score_name, "score": score, "wall_time_s": float(metrics["wall_time_s"]),
        "threads": None, "command": str(metrics["command"]),
        "config": {"overrides": None, "resolved": config_file.read_text() if config_file.exists() else None},
        "git_commit": metrics.get("git_commit"), "machine": metrics.get("machine"), "run_dir": str(run_dir),
        "metrics_file": str(metrics_file), "metrics": metrics, "imported_from": str(run_dir),
    }
    write_cell_json(out, record)
    print(f"[table1] imported {out.name} from {run_dir}: {score_name} = {score:.4f}", flush=True)
    return record


def run_cell(method: str, task: str, seed: int, *, teacher: str, preset: str, extra: list[str],
             runs_dir: Path, results_dir: Path, threads: int = 1, ftb_config: str | None = None,
             python: str = sys.executable) -> dict[str, Any] | None:
    """Run one cell (skipped if its JSON exists); returns the record, or ``None`` on failure.

    ``ftb_config``: the FTB recipe's hydra config name (``--config-name``; default ``ftb_offline``).
    """
    out = cell_path(results_dir, method, task, teacher, seed)
    if out.exists():
        print(f"[table1] skip {out.name} (done)")
        return json.loads(out.read_text())
    run_dir = runs_dir / task / teacher / method / f"seed{seed}"
    # both recipes: run_dir (hydra.run.dir follows it); resume=true continues a killed cell
    common = [*task_overrides(task), f"seed={seed}", f"labels.teacher={teacher}", f"preset={preset}",
              f"run_dir={run_dir}", "resume=true", "progress=false"]
    if method == "ftb":
        config = ["--config-name", ftb_config] if ftb_config else []
        cmd = [python, str(ROOT / "recipes" / "ftb_offline.py"), *config, *common, *extra]
    else:
        cmd = [python, str(ROOT / "recipes" / "baselines.py"), f"method={method}", *common, *extra]
    print(f"[table1] run {out.name}: {shlex.join(cmd)}", flush=True)
    start = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        log = runs_dir / "failed" / f"{out.stem}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(proc.stdout + "\n--- stderr ---\n" + proc.stderr)
        print(f"[table1] FAILED {out.name} (rc {proc.returncode}, {wall:.0f} s); log: {log}", flush=True)
        return None
    metrics_file = _find_metrics(run_dir)
    metrics = json.loads(metrics_file.read_text())
    score_name, score = _score_from_metrics(metrics)
    config_file = run_dir / "config.yaml"
    record = {
        "method": method, "env": task, "seed": seed, "teacher": teacher, "preset": preset,
        "score_name": score_name, "score": score, "wall_time_s": wall, "threads": threads,
        "command": shlex.join(cmd), "config": {"overrides": cmd[2:],
                                               "resolved": config_file.read_text() if config_file.exists() else None},
        "git_commit": git_commit(), "machine": machine_info(), "run_dir": str(run_dir),
        "metrics_file": str(metrics_file), "metrics": metrics,
    }
    write_cell_json(out, record)
    print(f"[table1] done {out.name}: {score_name} = {score:.4f} ({wall:.0f} s)", flush=True)
    return record


# ====================================================================
# Markdown
# --------


def load_cells(results_dir: Path) -> list[dict[str, Any]]:
    cells = []
    for path in sorted(Path(results_dir).glob("*.json")):
        try:
            record = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}: corrupt cell JSON ({err})") from err
        for key in ("method", "env", "seed", "score"):
            if key not in record:
                raise ValueError(f"{path}: cell JSON lacks {key!r}")
        cells.append(record)
    return cells


def _mean_std(values: list[float]) -> tuple[float, float]:
    mean = sum(values) / len(values)
    return mean, math.sqrt(sum((v - mean) ** 2 for v in values) / len(values))


def _fmt(value: float, *, big: bool) -> str:
    return f"{value:.1f}" if big else f"{value:.2f}"


def render_table(cells: list[dict[str, Any]], *, source: str = "bench/results/table1",
                 command: str = "python bench/table1.py --write-md") -> str:
    """The Markdown section: ours (mean ± std over seeds, n shown) beside the paper's numbers."""
    teachers = sorted({c.get("teacher", "return") for c in cells}) or ["return"]
    lines = [
        "Success rate (Meta-World) / D4RL-normalised score (locomotion); **ours**: mean ± std over "
        "seeds (population std), `n` = number of seeds; **[paper …]**: the paper's Table 1 "
        "(scripted teacher, 5 seeds; its offline-RL columns are CORL's numbers), shown for reference only. "
        "Our datasets are *generated here* (Meta-World v3 with the IPL recipe, our own locomotion "
        "behaviour data), not D4RL's or IPL's files, and our tasks are v3 where the paper's are v2, "
        "so the numbers are not directly comparable. "
        f"Generated by `{command}` from `{source}/*.json`.",
        "",
    ]
    if not cells:
        return "\n".join(lines + ["_No cells run yet._"])
    for teacher in teachers:
        sub = [c for c in cells if c.get("teacher", "return") == teacher]
        methods = [m for m in METHOD_NAMES if any(c["method"] == m for c in sub)]
        tasks = sorted({c["env"] for c in sub})
        presets = sorted({str(c.get("preset", "?")) for c in sub})
        lines += [f"**Teacher: `{teacher}`** (preset: {', '.join(presets)})", "",
                  "| task | " + " | ".join(METHOD_NAMES[m] for m in methods) + " |",
                  "|---|" + "---|" * len(methods)]
        for task in tasks:
            ptask = paper_task(task)
            row = [task + (f" (paper: {ptask})" if ptask and ptask != task else "")]
            for m in methods:
                vals = [float(c["score"]) for c in sub if c["method"] == m and c["env"] == task]
                big = any(abs(v) > 2.0 for v in vals)
                text = "—"
                if vals:
                    mean, std = _mean_std(vals)
                    text = f"{_fmt(mean, big=big)} ± {_fmt(std, big=big)} (n={len(vals)})"
                paper = PAPER_TABLE1.get(ptask, {}).get(m) if ptask else None
                if paper is not None:
                    text += f" [paper {paper if isinstance(paper, str) else _fmt(paper, big=big or paper > 2)}]"
                row.append(text)
            lines.append("| " + " | ".join(row) + " |")
        lines.append("")
    return "\n".join(lines).rstrip()


def _gb(cell: dict[str, Any]) -> float | None:
    mb = (cell.get("metrics", {}).get("machine") or {}).get("peak_rss_mb")
    return mb / 1024 if isinstance(mb, (int, float)) else None


def render_flow_table(cells: list[dict[str, Any]]) -> str:
    """FTB cells only: what the flow did (paper §4.3, Fig. 4 left) and what the run cost."""
    rows = [c for c in cells if c["method"] == "ftb" and isinstance(c.get("metrics", {}).get("flow"), dict)]
    if not rows:
        return ""
    filled = any("true_return_filled_mean_before" in c["metrics"]["flow"] for c in rows)
    lines = [
        "**FTB cells: the flow (final set vs. the original top-k) and the cost.** `valid` / `accept`: "
        "share of the first flow step's samples that were valid / accepted; *true return* of "
        "generated Meta-World trajectories is the simulator-replayed reward (`metaworld_true_reward`, "
        "up to 16 % error, BENCHMARKS § datasets); locomotion: the oracle reward of the generated "
        "(s, a) pairs. `wall`: the whole cell, other jobs sharing the 2 cores."
        + (" *Filled*: the same true return with the stop-rule fill (a trajectory shorter than "
           "`flow.true_return_horizon` keeps earning its last reward; a faster success earns more)."
           if filled else ""),
        "",
        "| task | teacher | seed | flow steps | accepted | valid / accept | score mean before → after | "
        "true return mean before → after | true return max before → after | "
        + ("filled mean before → after | filled max before → after | " if filled else "")
        + "policy score | wall (min) | peak RSS (GB) |",
        "|---|---|---|---|---|---|---|---|---|" + ("---|---|" if filled else "") + "---|---|---|",
    ]

    def num(value: Any, fmt: str = "{:.1f}") -> str:
        return fmt.format(value) if isinstance(value, (int, float)) else "—"

    for c in sorted(rows, key=lambda c: (c["env"], c.get("teacher", ""), c["seed"])):
        f = c["metrics"]["flow"]
        first = (c["metrics"].get("flow_stats") or [{}])[0]
        lines.append(
            f"| {c['env']} | {c.get('teacher', 'return')} | {c['seed']} | {num(f.get('flow_steps_run'), '{:.0f}')} | "
            f"{num(f.get('num_generated_accepted'), '{:.0f}')} | "
            f"{num(first.get('valid_rate'), '{:.2f}')} / {num(first.get('accept_rate'), '{:.2f}')} | "
            f"{num(f.get('score_mean_before'))} → {num(f.get('score_mean_after'))} | "
            f"{num(f.get('true_return_mean_before'))} → {num(f.get('true_return_mean_after'))} | "
            f"{num(f.get('true_return_max_before'))} → {num(f.get('true_return_max_after'))} | "
            + (f"{num(f.get('true_return_filled_mean_before'))} → {num(f.get('true_return_filled_mean_after'))} | "
               f"{num(f.get('true_return_filled_max_before'))} → {num(f.get('true_return_filled_max_after'))} | "
               if filled else "")
            + f"{num(c.get('score'), '{:.2f}')} | {num(c.get('wall_time_s', 0) / 60)} | "
            f"{num(_gb(c), '{:.2f}')} |"
        )
    return "\n".join(lines)


def pooled_success(cells: list[dict[str, Any]], *, confidence: float = 0.95) -> tuple[int, int, float, float] | None:
    """Successes and episodes of success-rate cells pooled over seeds, with a Wilson interval.

    Args:
        cells: cell records of one method, task and configuration (one per seed).
        confidence: level of the interval.

    Returns:
        ``(successes, episodes, low, high)``, or ``None`` when a cell is not a success rate or does not
        record its number of episodes (``metrics.eval.num_episodes``). The interval treats the pooled
        episodes as independent: it is episode noise only, the seed-to-seed spread is the ± s.e.

    Example:
        >>> cell = {"score_name": "success_rate", "score": 0.0, "metrics": {"eval": {"num_episodes": 50}}}
        >>> k, n, low, high = pooled_success([cell, cell, cell])
        >>> (k, n, low, round(high, 3))
        (0, 150, 0.0, 0.025)
    """
    from scipy.stats import binomtest  # scikit-learn's dependency; Wilson's interval, not hand-written

    successes = episodes = 0
    for cell in cells:
        num = cell.get("metrics", {}).get("eval", {}).get("num_episodes")
        if cell.get("score_name") != "success_rate" or not isinstance(num, int) or num <= 0:
            return None
        k = round(float(cell["score"]) * num)
        if abs(k - float(cell["score"]) * num) > 1e-6:
            raise ValueError(f"cell {cell.get('env')} seed {cell.get('seed')}: success rate {cell['score']} is "
                             f"not a whole number of successes in {num} episodes")
        successes, episodes = successes + k, episodes + num
    interval = binomtest(successes, episodes).proportion_ci(confidence_level=confidence, method="wilson")
    return successes, episodes, float(interval.low), float(interval.high)


def render_comparison(configs: dict[str, Path], *, teacher: str, method: str = "ftb") -> str:
    """One method under several configurations (one results directory each), task by task.

    Each cell: mean ± standard error over seeds (population std / sqrt(n)), ``n`` and the per-seed
    scores in seed order, beside the paper's number; what the *best per task* and *one setting for
    every task* questions of issue #5 need, read from the cell JSONs instead of copied by hand.
    Success rates also get their episodes pooled over seeds, ``k/N ep.``, with a 95 % Wilson
    interval (:func:`pooled_success`): with 20-50 episodes a seed, whether a gap to the paper is
    more than episode noise (assembly: 0 of 120 vs the paper's 0.02) is read from the table.
    """
    table: dict[str, dict[str, dict[int, dict[str, Any]]]] = {}  # task -> label -> seed -> cell
    for label, results_dir in configs.items():
        for c in load_cells(results_dir):
            if c["method"] == method and c.get("teacher", "return") == teacher:
                table.setdefault(c["env"], {}).setdefault(label, {})[int(c["seed"])] = c
    lines = [f"**{METHOD_NAMES.get(method, method)}, teacher `{teacher}`**: mean ± s.e. over seeds (n; per seed)",
             "", "| task | " + " | ".join(configs) + " | paper |", "|---|" + "---|" * (len(configs) + 1)]
    for task in sorted(table):
        row = [task]
        for label in configs:
            per_seed = {seed: float(c["score"]) for seed, c in table[task].get(label, {}).items()}
            if not per_seed:
                row.append("—")
                continue
            vals = [per_seed[k] for k in sorted(per_seed)]
            big = any(abs(v) > 2.0 for v in vals)
            mean, std = _mean_std(vals)
            labelled = sorted(per_seed) != list(range(len(vals)))  # name the seeds when some are missing
            seeds = " / ".join((f"s{k} " if labelled else "") + _fmt(per_seed[k], big=big) for k in sorted(per_seed))
            pooled = pooled_success(list(table[task][label].values()))
            episodes = "" if pooled is None else f"; {pooled[0]}/{pooled[1]} ep., 95 % CI {pooled[2]:.2f}–{pooled[3]:.2f}"
            row.append(f"{_fmt(mean, big=big)} ± {_fmt(std / math.sqrt(len(vals)), big=big)} "
                       f"(n={len(vals)}; {seeds}{episodes})")
        ptask = paper_task(task)
        paper = PAPER_TABLE1.get(ptask, {}).get(method) if ptask else None
        row.append("—" if paper is None else str(paper))
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def write_markdown(results_dir: Path, md_path: Path, *, section: str = "table1") -> None:
    """Replace the ``section``'s marked part of ``md_path`` (created or appended if absent), atomically."""
    start, end = markers(section)
    cells = load_cells(results_dir)
    try:
        source = str(Path(results_dir).resolve().relative_to(ROOT))
    except ValueError:
        source = str(results_dir)
    command = "python bench/table1.py --write-md" + (
        "" if section == "table1" else f" --results-dir {source} --section {section}")
    body = render_table(cells, source=source, command=command)
    flow = render_flow_table(cells)
    block = f"{start}\n{body}\n\n{flow}\n{end}" if flow else f"{start}\n{body}\n{end}"
    text = md_path.read_text() if md_path.exists() else "# Benchmarks\n"
    if start in text and end in text and text.index(start) < text.index(end):
        text = text[: text.index(start)] + block + text[text.index(end) + len(end):]
    else:
        text = text.rstrip() + f"\n\n## Table 1 (scripted teachers; {source})\n\n" + block + "\n"
    fd, tmp = tempfile.mkstemp(dir=md_path.parent, prefix=f".{md_path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, md_path)
    print(f"[table1] wrote {md_path}")


# ====================================================================
# CLI
# ---


def _csv(value: str) -> list[str]:
    return [v.strip() for v in value.split(",") if v.strip()]


def main(argv: Iterable[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", type=_csv, default=["bc10", "td3bc", "iql", "iql_rpsi", "oprl", "ftb"])
    parser.add_argument("--tasks", type=_csv, default=["button-press-v3"])
    parser.add_argument("--seeds", type=_csv, default=["0"])
    parser.add_argument("--teacher", default="return", help="scripted teacher: return (paper) | success")
    parser.add_argument("--preset", default="cpu", help="recipe preset: cpu | paper")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS (torch threads) per cell")
    parser.add_argument("--extra", nargs="*", default=[], help="extra hydra overrides for every cell")
    parser.add_argument("--ftb-config", default=None,
                        help="hydra config of the ftb cells, e.g. ftb_offline_metaworld (default: ftb_offline)")
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "outputs" / "table1")
    parser.add_argument("--write-md", action="store_true", help="only (re)write the BENCHMARKS.md section")
    parser.add_argument("--md", type=Path, default=ROOT / "BENCHMARKS.md")
    parser.add_argument("--section", default="table1",
                        help="with --write-md: the BENCHMARKS.md section (markers <!-- NAME:start/end -->)")
    parser.add_argument("--import-run", type=Path, nargs="+", default=None, metavar="RUN_DIR",
                        help="write the cells of finished recipe runs made outside the harness, then stop")
    parser.add_argument("--dry-run", action="store_true", help="list the cells and whether they are done")
    parser.add_argument("--compare", nargs="+", default=None, metavar="LABEL=DIR",
                        help="print one method (first of --methods) under several configurations, one results "
                             "directory each, for --teacher, then stop")
    args = parser.parse_args(list(argv) if argv is not None else None)

    if args.compare:
        configs = {}
        for item in args.compare:
            label, sep, path = item.rpartition("=")  # labels may hold "=" (k=200)
            if not sep or not label or not path:
                parser.error(f"--compare: expected LABEL=DIR, got {item!r}")
            if not Path(path).is_dir():
                parser.error(f"--compare: {path!r} is not a directory")
            configs[label] = Path(path)
        print(render_comparison(configs, teacher=args.teacher, method=args.methods[0]))
        return 0
    if args.write_md:
        write_markdown(args.results_dir, args.md, section=args.section)
        return 0
    if args.import_run:
        for run_dir in args.import_run:
            import_run(run_dir, results_dir=args.results_dir)
        return 0
    unknown = [m for m in args.methods if m not in METHOD_NAMES]
    if unknown:
        parser.error(f"unknown methods {unknown}; choose from {list(METHOD_NAMES)}")
    failures = 0
    for task in args.tasks:
        for seed in map(int, args.seeds):
            for method in args.methods:
                path = cell_path(args.results_dir, method, task, args.teacher, seed)
                if args.dry_run:
                    print(f"{'done' if path.exists() else 'todo'}  {path.name}")
                    continue
                if run_cell(method, task, seed, teacher=args.teacher, preset=args.preset, extra=args.extra,
                            threads=args.threads, ftb_config=args.ftb_config,
                            runs_dir=args.runs_dir, results_dir=args.results_dir) is None:
                    failures += 1
    if failures:
        print(f"[table1] {failures} cell(s) failed (see {args.runs_dir / 'failed'})")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
