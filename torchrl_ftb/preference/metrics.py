"""How faithful is the learned preference? (paper §4.2, Fig. 3).

Trajectory level: Pearson / Spearman of ``s_psi(tau)`` with the true return (and with
success when given), pairwise accuracy on held-out labels. Transition level: the same
correlations of the per-step ``r_psi(s, a)`` with the true per-step reward — with the
MLP-sum score model ``r_psi`` *is* the transition-wise reward model "trained the usual way"
(Bradley–Terry on summed rewards), so both views of one model are reported, as in Fig. 3.

Example:
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=16, horizon=8, seed=0)
    >>> returns = trajs["next", "reward"].squeeze(-1).sum(-1)
    >>> m = preference_metrics(ScoreModel(3, 2, num_cells=8, seed=0), trajs, true_returns=returns)
    >>> sorted(k for k in m if k.startswith("trajectory"))
    ['trajectory_pearson_return', 'trajectory_spearman_return']
"""
from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch
from scipy import stats
from tensordict import TensorDictBase

from torchrl_ftb.preference.loss import preference_accuracy
from torchrl_ftb.preference.score import ScoreModel, score_trajectories

__all__ = ["preference_metrics", "pairwise_accuracy", "plot_preference_scatter", "correlations", "top_k_mean"]


def correlations(x: torch.Tensor, y: torch.Tensor) -> dict[str, float]:
    """``{"pearson", "spearman"}`` of two 1-D tensors (scipy); NaN when either is constant."""
    x = x.detach().double().cpu().numpy().ravel()
    y = y.detach().double().cpu().numpy().ravel()
    if x.shape != y.shape or x.size < 2:
        raise ValueError(f"correlations: need two equally long vectors of >= 2 values, got {x.shape}, {y.shape}")
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return {"pearson": float("nan"), "spearman": float("nan")}
    return {"pearson": float(stats.pearsonr(x, y)[0]), "spearman": float(stats.spearmanr(x, y)[0])}


def top_k_mean(scores: torch.Tensor, values: torch.Tensor, k: int) -> float:
    """Mean of ``values`` over the ``k`` highest-scoring entries (ties broken by ``torch.topk``).

    With ``values`` the per-trajectory success this is the share of successes among the
    trajectories FTB starts from (``flow.top_k``), the data its BC policy mostly learns from.

    Example:
        >>> top_k_mean(torch.tensor([0.1, 0.9, 0.5, 0.7]), torch.tensor([1.0, 1.0, 0.0, 0.0]), 2)
        0.5
    """
    scores, values = scores.detach().reshape(-1), values.detach().reshape(-1)
    if scores.shape != values.shape:
        raise ValueError(f"top_k_mean: scores {list(scores.shape)} and values {list(values.shape)} differ")
    if not 1 <= k <= scores.numel():
        raise ValueError(f"top_k_mean: k={k} must be in [1, {scores.numel()}]")
    return float(values.double()[scores.topk(k).indices.to(values.device)].mean())


@torch.no_grad()
def pairwise_accuracy(model: ScoreModel, labels: TensorDictBase, *, batch_size: int = 256) -> float:
    """Fraction of non-tie labelled pairs the model ranks as labelled (NaN if all are ties)."""
    s0 = score_trajectories(model, labels.get("tau0"), batch_size=batch_size)
    s1 = score_trajectories(model, labels.get("tau1"), batch_size=batch_size)
    return float(preference_accuracy(s0, s1, labels.get("label").to(s0.device)))


@torch.no_grad()
def preference_metrics(
    model: ScoreModel,
    trajs: TensorDictBase,
    *,
    true_returns: torch.Tensor,
    success: torch.Tensor | None = None,
    labels: TensorDictBase | None = None,
    reward_key=("next", "reward"),
    batch_size: int = 1024,
) -> dict[str, float]:
    """Correlation of the learned score/reward with the ground truth, as plain floats.

    Args:
        model: trained :class:`ScoreModel`.
        trajs: ``[N, H]`` trajectories to evaluate on (e.g. the unlabelled dataset).

    Keyword Args:
        true_returns: ``[N]`` ground-truth returns (same discount as the labels' teacher).
        success: optional ``[N]`` per-trajectory success (bool or 0/1).
        labels: optional held-out labels for ``pairwise_accuracy``.
        reward_key: per-step true reward in ``trajs``; transition metrics are skipped when absent.
        batch_size: scoring chunk size.

    Returns:
        ``trajectory_{pearson,spearman}_return``, ``trajectory_{pearson,spearman}_success``
        (with ``success``), ``transition_{pearson,spearman}_reward`` (when ``reward_key`` is
        present; valid steps only), ``pairwise_accuracy`` (with ``labels``), ``num_trajectories``,
        ``num_transitions``. Correlations are NaN when an input is constant.
    """
    n = trajs.batch_size[0]
    true_returns = torch.as_tensor(true_returns).reshape(-1)
    if true_returns.numel() != n:
        raise ValueError(f"preference_metrics: true_returns has {true_returns.numel()} values for {n} trajectories")
    scores = score_trajectories(model, trajs, batch_size=batch_size)
    out: dict[str, float] = {"num_trajectories": float(n)}
    for name, value in correlations(scores, true_returns).items():
        out[f"trajectory_{name}_return"] = value
    if success is not None:
        success = torch.as_tensor(success).reshape(-1).float()
        if success.numel() != n:
            raise ValueError(f"preference_metrics: success has {success.numel()} values for {n} trajectories")
        for name, value in correlations(scores, success).items():
            out[f"trajectory_{name}_success"] = value
    if reward_key in trajs.keys(True):
        learned, true = _transition_rewards(model, trajs, reward_key=reward_key, batch_size=batch_size)
        out["num_transitions"] = float(true.numel())
        for name, value in correlations(learned, true).items():
            out[f"transition_{name}_reward"] = value
    if labels is not None:
        out["pairwise_accuracy"] = pairwise_accuracy(model, labels, batch_size=batch_size)
    return out


@torch.no_grad()
def _transition_rewards(model: ScoreModel, trajs: TensorDictBase, *, reward_key, batch_size: int):
    """Learned ``r_psi`` and true reward on the valid steps (flat)."""
    device = model.gamma.device
    learned, true = [], []
    for i in range(0, trajs.batch_size[0], batch_size):
        chunk = trajs[i : i + batch_size]
        mask = chunk.get("mask")
        r = model.step_rewards(chunk.to(device)).mean(0).cpu()
        learned.append(r[mask.cpu()])
        true.append(chunk.get(reward_key).reshape(mask.shape)[mask].cpu())
    return torch.cat(learned), torch.cat(true)


def plot_preference_scatter(
    model: ScoreModel,
    trajs: TensorDictBase,
    path: str | os.PathLike,
    *,
    true_returns: torch.Tensor,
    reward_key=("next", "reward"),
    title: str | None = None,
    max_points: int = 5000,
    seed: int = 0,
) -> Path:
    """Fig. 3-style scatter PNG: learned vs true reward (per step) and score vs return (per trajectory).

    The reward panel is drawn only when ``reward_key`` is in ``trajs``; at most ``max_points``
    transitions are plotted (seeded subsample). Written atomically (temp file + ``os.replace``).

    Returns:
        The PNG path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scores = score_trajectories(model, trajs).cpu()
    true_returns = torch.as_tensor(true_returns).reshape(-1).cpu()
    with_reward = reward_key in trajs.keys(True)
    fig, axes = plt.subplots(1, 2 if with_reward else 1, figsize=(9 if with_reward else 4.5, 4), squeeze=False)
    panels = []
    if with_reward:
        learned, true = _transition_rewards(model, trajs, reward_key=reward_key, batch_size=1024)
        if true.numel() > max_points:
            keep = torch.randperm(true.numel(), generator=torch.Generator().manual_seed(seed))[:max_points]
            learned, true = learned[keep], true[keep]
        panels.append((true, learned, "true reward", "learned reward r_psi(s, a)", "transition-wise"))
    panels.append((true_returns, scores, "true return", "learned score s_psi(tau)", "trajectory-wise"))
    for ax, (x, y, xl, yl, kind) in zip(axes[0], panels):
        c = correlations(y, x)
        ax.scatter(x.numpy(), y.numpy(), s=4, alpha=0.5)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(f"{kind}: pearson {c['pearson']:.2f}, spearman {c['spearman']:.2f}", fontsize=9)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".png")
    os.close(fd)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fig.savefig(tmp, format="png", dpi=120)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    finally:
        plt.close(fig)
    return path
