"""Provenance of a run or benchmark: git commit, machine, command, and its JSON record.

One home for what every recipe (``recipes/*.py``) and benchmark (``bench/*.py``) writes
beside its results, plus the torchrl logger the recipes open. Importing this module is
cheap (one ``git rev-parse``: the commit of the loaded code): ``torch`` and ``torchrl`` are
imported only by the functions that need them.

Example:
    >>> import tempfile
    >>> from pathlib import Path
    >>> from torchrl_ftb.provenance import run_record, write_json
    >>> record = run_record(command="python demo.py", config={"seed": 0})
    >>> sorted(record)
    ['command', 'config', 'git_commit', 'machine', 'timestamp']
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = write_json(Path(tmp) / "run.json", record)
    ...     path.name
    'run.json'
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

__all__ = ["git_commit", "machine_info", "run_record", "write_json", "make_logger"]

#: the folder of this package: inside the repository for a source / editable install
PACKAGE_DIR = Path(__file__).resolve().parent


def _rev_parse(cwd: str | os.PathLike) -> str | None:
    """``git rev-parse HEAD`` in ``cwd``, or None (no git, not a checkout, no answer within 10 s)."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return (out.stdout.strip() or None) if out.returncode == 0 else None


#: the commit checked out when this process imported the package, i.e. the code it runs: a commit
#: made in the same tree while a long run works (its results are written at the end) is not it
_LOADED_COMMIT = _rev_parse(PACKAGE_DIR)


def git_commit(cwd: str | os.PathLike | None = None) -> str | None:
    """The commit of the code this process runs, or the one checked out in ``cwd``.

    Args:
        cwd: a folder inside a git checkout, asked now. Default: this package's checkout as it
            was when the package was imported (a recipe that runs for an hour records the commit
            it started with, not one made in the tree meanwhile).

    Returns:
        The 40-hex commit, or ``None`` when git is missing, the folder is not in a checkout,
        or git does not answer within 10 s.

    Example:
        >>> from torchrl_ftb.provenance import git_commit
        >>> commit = git_commit()
        >>> commit is None or len(commit) == 40
        True
    """
    return _LOADED_COMMIT if cwd is None else _rev_parse(cwd)


def _cpu_model() -> str | None:
    """``model name`` from ``/proc/cpuinfo`` (Linux), else ``None``."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip() or None
    except OSError:
        pass
    return None


def _load_avg_1m() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):  # not on Windows; OSError when unobtainable
        return None


def _peak_rss_mb() -> float | None:
    try:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
    except (ImportError, OSError):  # no ``resource`` on Windows
        return None


def machine_info() -> dict[str, Any]:
    """What the numbers of a run depend on: hardware, load and software versions.

    Returns:
        ``{"platform", "processor", "cpu", "cpu_count", "python", "torch", "threads",
        "cuda", "load_avg_1m", "peak_rss_mb"}``: ``cpu`` is the CPU model name from ``/proc/cpuinfo``
        (``None`` where unavailable), ``threads`` torch's intra-op threads, ``cuda`` the
        name of CUDA device 0 or ``None``, ``load_avg_1m`` the 1-minute load average or
        ``None``, ``peak_rss_mb`` this process's peak resident memory so far (MiB, Linux).

    Example:
        >>> from torchrl_ftb.provenance import machine_info
        >>> info = machine_info()
        >>> info["cpu_count"] >= 1 and info["threads"] >= 1
        True
    """
    import torch

    return {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "load_avg_1m": _load_avg_1m(),
        "peak_rss_mb": _peak_rss_mb(),
    }


def run_record(*, command: str | None = None, config: Any = None) -> dict[str, Any]:
    """The provenance block of a results file.

    Args:
        command: the command line; default: this interpreter and ``sys.argv``.
        config: the run's configuration (any JSON-able object; see :func:`write_json`).

    Returns:
        ``{"command", "config", "git_commit", "machine", "timestamp"}`` with
        ``machine`` from :func:`machine_info` and ``timestamp`` in ISO format, UTC.

    Example:
        >>> from torchrl_ftb.provenance import run_record
        >>> run_record(command="python bench/x.py", config={"steps": 3})["config"]
        {'steps': 3}
    """
    return {
        "command": command if command is not None else " ".join([sys.executable, *sys.argv]),
        "config": config,
        "git_commit": git_commit(),
        "machine": machine_info(),
        "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def _json_default(obj: Any) -> Any:
    """Tensors and numpy values → ``.tolist()`` (numbers or lists); anything else → ``str``.

    A TensorDict (which also has ``tolist``) stays a ``str``: it is a summary, not data.
    """
    torch, np = sys.modules.get("torch"), sys.modules.get("numpy")  # a tensor implies torch is loaded
    if (torch is not None and isinstance(obj, torch.Tensor)) or (
            np is not None and isinstance(obj, (np.ndarray, np.generic))):
        return obj.tolist()
    return str(obj)


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically (temp file + ``os.replace``).

    Tensors and numpy arrays/scalars are written as numbers or lists, paths and any other
    non-JSON object as their ``str``. Missing parent folders are created.

    Args:
        path: the JSON file.
        obj: the object to write.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Example:
        >>> import json, tempfile, torch
        >>> from pathlib import Path
        >>> from torchrl_ftb.provenance import write_json
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     path = write_json(Path(tmp) / "a" / "m.json", {"x": torch.tensor([1, 2]), "p": Path("r")})
        ...     json.loads(path.read_text())
        {'x': [1, 2], 'p': 'r'}
    """
    from torchrl_ftb.data.trajectories import atomic_write_text  # imports torch: keep this module light

    atomic_write_text(path, json.dumps(obj, indent=2, default=_json_default))
    return Path(path)


def make_logger(backend: str, *, log_dir: str | os.PathLike, experiment_name: str, project: str = "torchrl_ftb",
                mode: str = "offline", config: dict | None = None):
    """A torchrl logger (:func:`torchrl.record.loggers.get_logger`), or ``None``.

    Args:
        backend: ``"csv"``, ``"tensorboard"``, ``"wandb"``, ``"mlflow"``, ...; empty or
            ``None``: no logger.
        log_dir: the folder the logger writes under.
        experiment_name: the run's name.
        project: wandb project.
        mode: wandb mode (``"offline"``, ``"online"``, ``"disabled"``).
        config: the run's configuration, recorded by wandb.

    Returns:
        A :class:`torchrl.record.loggers.Logger`, or ``None`` when ``backend`` is empty.

    Example:
        >>> import tempfile
        >>> from torchrl_ftb.provenance import make_logger
        >>> make_logger("", log_dir="unused", experiment_name="demo") is None
        True
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     logger = make_logger("csv", log_dir=tmp, experiment_name="demo")
        ...     logger.log_scalar("loss", 0.5, step=0)
    """
    if not backend:
        return None
    from torchrl.record.loggers import get_logger

    wandb_kwargs = {"project": project, "mode": mode, "config": config}
    return get_logger(backend, logger_name=str(log_dir), experiment_name=experiment_name,
                      wandb_kwargs=wandb_kwargs)
