"""Plots of the flow and the analyses (matplotlib, Agg backend, PNG files written atomically).

Example:
    >>> import tempfile, torch
    >>> from pathlib import Path
    >>> d = Path(tempfile.mkdtemp())
    >>> stats = [{"step": 1, "score_mean": 1.0, "score_max": 2.0}, {"step": 2, "score_mean": 1.5, "score_max": 2.5}]
    >>> plot_flow_curves(stats, d / "flow.png", before={"score_mean": 0.5, "score_max": 1.5}).exists()
    True
    >>> plot_histograms({"before": torch.randn(50), "after": torch.randn(50) + 1}, d / "h.png", xlabel="return").exists()
    True
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

__all__ = ["plot_curves", "plot_flow_curves", "plot_histograms", "plot_scatter", "save_figure"]


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Save ``fig`` as PNG atomically (temp file + ``os.replace``) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".png")
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def plot_flow_curves(
    stats: Sequence[Mapping[str, float]],
    path: str | os.PathLike,
    *,
    before: Mapping[str, float] | None = None,
    title: str = "Flow to better",
) -> Path:
    """Score (and true return, if present) of the current set per flow step; step 0 = ``before``.

    Args:
        stats: per-step dicts from :class:`~torchrl_ftb.flow.FlowToBetter` (``score_mean``,
            ``score_max``, optional ``true_return_mean``/``true_return_max``, ``accept_rate``).
        path: PNG file.
        before: the same keys for the original top-k (plotted at step 0).
    """
    rows = ([{"step": 0, **before}] if before else []) + [dict(r) for r in stats]
    panels = [("score", "score s_psi")]
    if any("true_return_mean" in r for r in rows):
        panels.append(("true_return", "true return"))
    if any("accept_rate" in r for r in rows):
        panels.append(("accept_rate", "accept rate"))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4), squeeze=False)
    for ax, (key, label) in zip(axes[0], panels):
        for suffix, style in (("_mean", "o-"), ("_max", "s--"), ("", "o-")):
            name = key + suffix
            pts = [(r["step"], r[name]) for r in rows if name in r]
            if pts and (suffix or key == "accept_rate"):
                ax.plot(*zip(*pts), style, label=(suffix.strip("_") or key))
        ax.set_xlabel("flow step")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if key != "accept_rate":
            ax.legend()
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_curves(
    curves: Mapping[str, torch.Tensor | Sequence[float]],
    path: str | os.PathLike,
    *,
    xlabel: str,
    ylabel: str,
    levels: Mapping[str, float] | None = None,
    title: str = "",
    log_y: bool = False,
) -> Path:
    """Named curves over their index (NaN points left out), with named horizontal ``levels`` dashed, e.g. the
    generated transitions' dynamics error by step beside a learned model's error (paper Fig. 4 right).

    Example:
        >>> plot_curves({"a": [1.0, 2.0]}, "/tmp/curves.png", xlabel="h", ylabel="e", levels={"ref": 1.5})  # doctest: +SKIP
    """
    fig, ax = plt.subplots(figsize=(5.6, 3.4))
    for name, values in curves.items():
        v = torch.as_tensor(values, dtype=torch.float64).flatten()
        keep = torch.isfinite(v)
        ax.plot(torch.arange(len(v))[keep].tolist(), v[keep].tolist(), label=name)
    for i, (name, value) in enumerate((levels or {}).items()):
        ax.axhline(float(value), linestyle="--", color=f"C{len(curves) + i}", label=f"{name} ({float(value):.3g})")
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_histograms(
    values: Mapping[str, torch.Tensor | Sequence[float]],
    path: str | os.PathLike,
    *,
    xlabel: str,
    title: str = "",
    bins: int = 30,
) -> Path:
    """Overlaid histograms of several named samples (e.g. before vs after the flow)."""
    fig, ax = plt.subplots(figsize=(5, 3.4))
    arrays = {k: torch.as_tensor(v, dtype=torch.float64).flatten() for k, v in values.items()}
    arrays = {k: v[torch.isfinite(v)] for k, v in arrays.items() if v.numel()}
    if arrays:
        lo = min(float(v.min()) for v in arrays.values())
        hi = max(float(v.max()) for v in arrays.values())
        edges = torch.linspace(lo, hi if hi > lo else lo + 1.0, bins + 1).tolist()
        for name, v in arrays.items():
            ax.hist(v.tolist(), bins=edges, alpha=0.55, label=f"{name} (mean {float(v.mean()):.3g})")
        ax.legend()
    ax.set_xlabel(xlabel)
    ax.set_ylabel("trajectories")
    ax.set_title(title)
    return save_figure(fig, path)


def plot_scatter(
    x: torch.Tensor | Sequence[float],
    y: torch.Tensor | Sequence[float],
    path: str | os.PathLike,
    *,
    xlabel: str,
    ylabel: str,
    title: str = "",
    highlight: torch.Tensor | Sequence[bool] | None = None,
    highlight_label: str = "",
) -> Path:
    """One point per item with the diagonal ``y = x`` (e.g. a sample's return claimed by its states vs
    replayed in the simulator); ``highlight`` marks some points (e.g. replays that succeed).

    Example:
        >>> plot_scatter([1.0, 2.0], [0.5, 2.5], "/tmp/scatter.png", xlabel="claimed", ylabel="replayed")  # doctest: +SKIP
    """
    xs = torch.as_tensor(x, dtype=torch.float64).flatten()
    ys = torch.as_tensor(y, dtype=torch.float64).flatten()
    if xs.shape != ys.shape:
        raise ValueError(f"plot_scatter: {xs.numel()} x values but {ys.numel()} y values")
    fig, ax = plt.subplots(figsize=(4.4, 4.2))
    if xs.numel():
        mark = torch.zeros_like(xs, dtype=torch.bool) if highlight is None else torch.as_tensor(highlight).bool()
        ax.scatter(xs[~mark].tolist(), ys[~mark].tolist(), s=14, alpha=0.6)
        if bool(mark.any()):
            ax.scatter(xs[mark].tolist(), ys[mark].tolist(), s=24, marker="*", label=highlight_label or None)
            if highlight_label:
                ax.legend()
        both = torch.cat([xs, ys])
        lo, hi = float(both.min()), float(both.max())
        ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)
