"""Train the score model on preference labels with the Bradley–Terry loss (Alg. 2, lines 1-5).

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=8, horizon=8, seed=0).select("observation", "action", "mask")
    >>> labels = TensorDict({"tau0": trajs[:4], "tau1": trajs[4:],
    ...                      "label": torch.tensor([1.0, 0.0, 1.0, 0.5])}, [4])
    >>> out = train_score_model(ScoreModel(3, 2, num_cells=8, seed=0), labels, steps=5,
    ...                         eval_fraction=0.0, progress=False)
    >>> out["steps"]
    5
"""
from __future__ import annotations

import math
import warnings
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_ftb.data.labels import validate_labels
from torchrl_ftb.preference.loss import BradleyTerryLoss
from torchrl_ftb.preference.score import ScoreModel

__all__ = ["train_score_model", "split_labels"]


def split_labels(
    labels: TensorDictBase, *, eval_fraction: float, seed: int = 0
) -> tuple[TensorDictBase, TensorDictBase | None]:
    """Random train/held-out split; ``None`` held-out set when too few labels (warns).

    The held-out set has ``floor(M * eval_fraction)`` pairs; a split is only made when that
    is >= 1 and at least 2 pairs stay for training.
    """
    if not 0.0 <= eval_fraction < 1.0:
        raise ValueError(f"split_labels: eval_fraction must be in [0, 1), got {eval_fraction}")
    m = labels.batch_size[0]
    n_eval = int(math.floor(m * eval_fraction))
    if eval_fraction > 0 and (n_eval < 1 or m - n_eval < 2):
        warnings.warn(f"split_labels: {m} labels are too few for a held-out split; training on all", stacklevel=2)
        return labels, None
    if n_eval == 0:
        return labels, None
    perm = torch.randperm(m, generator=torch.Generator().manual_seed(seed))
    return labels[perm[n_eval:]], labels[perm[:n_eval]]


@torch.no_grad()
def _evaluate(loss_fn: BradleyTerryLoss, labels: TensorDictBase, chunk: int = 256) -> dict[str, float]:
    was_training = loss_fn.training
    loss_fn.eval()
    total, correct_w, n, n_decided = 0.0, 0.0, 0, 0
    for i in range(0, labels.batch_size[0], chunk):
        part = labels[i : i + chunk]
        out = loss_fn(part)
        size = part.batch_size[0]
        decided = int((part.get("label") != 0.5).sum())
        total += float(out["loss_preference"]) * size
        if decided:
            correct_w += float(out["accuracy"]) * decided
        n, n_decided = n + size, n_decided + decided
    loss_fn.train(was_training)
    result = {"loss": total / n}
    if n_decided:
        result["accuracy"] = correct_w / n_decided
    return result


def train_score_model(
    model: ScoreModel,
    labels: TensorDictBase,
    *,
    steps: int = 1000,
    batch_size: int = 256,
    lr: float = 1e-4,
    weight_decay: float = 0.0,
    max_grad_norm: float | None = None,
    eval_fraction: float = 0.2,
    eval_labels: TensorDictBase | None = None,
    eval_interval: int = 100,
    seed: int = 0,
    logger: Logger | None = None,
    log_prefix: str = "preference/",
    progress: bool = True,
    device: torch.device | str | None = None,
) -> dict[str, Any]:
    """Fit ``model`` to preference labels by minimising the Bradley–Terry loss with Adam.

    With ``M <= batch_size`` training labels every step uses all of them (full batch);
    otherwise batches are drawn uniformly with replacement from a torchrl replay buffer.

    Args:
        model: the :class:`ScoreModel` (moved to ``device`` in place; returned trained).
        labels: preference labels ``[M]`` (``tau0``, ``tau1``, ``label``).

    Keyword Args:
        steps: gradient steps.
        batch_size: pairs per step (Table 4: 256).
        lr: Adam learning rate (Table 4: 1e-4).
        weight_decay: Adam weight decay.
        max_grad_norm: gradient-norm clip (``None``: no clipping).
        eval_fraction: held-out share of ``labels`` when ``eval_labels`` is not given.
        eval_labels: explicit held-out labels (then all of ``labels`` train).
        eval_interval: steps between held-out evaluations (also at the end).
        seed: seeds the split and the batch sampling.
        logger: a torchrl logger; receives ``{log_prefix}train_loss``, ``train_accuracy``,
            ``eval_loss``, ``eval_accuracy`` (finite values only).
        progress: show a tqdm bar.
        device: training device (default: the model's).

    Returns:
        ``{"steps", "num_train", "num_eval", "train_loss", "train_accuracy", "eval_loss",
        "eval_accuracy", "history"}``; an accuracy is absent when its set has only ties,
        ``eval_*`` are absent without a held-out set. ``history`` lists the logged dicts.

    Raises:
        ValueError: fewer than 2 labels, only ties (no preference signal), malformed labels
            (:func:`torchrl_ftb.data.labels.validate_labels`).
        FloatingPointError: the scores or the loss become NaN/inf during training.
    """
    validate_labels(labels)
    if labels.batch_size[0] < 2:
        raise ValueError(f"train_score_model: need at least 2 labels, got {labels.batch_size[0]}")
    if steps < 1 or batch_size < 1:
        raise ValueError(f"train_score_model: steps and batch_size must be >= 1, got {steps}, {batch_size}")
    if eval_labels is not None:
        validate_labels(eval_labels, name="eval_labels")
        train, held_out = labels, eval_labels
    else:
        train, held_out = split_labels(labels, eval_fraction=eval_fraction, seed=seed)
    if not bool((train.get("label") != 0.5).any()):
        raise ValueError("train_score_model: all training labels are ties (0.5): no preference signal")

    device = torch.device(device) if device is not None else model.gamma.device
    model.to(device)
    loss_fn = BradleyTerryLoss(model)
    # keep only what the loss reads (drops e.g. the non-tensor "teacher" and unused keys; the termination flag
    # the stop-rule fill reads is optional: label files without it are filled as never terminated)
    train = train.select(*loss_fn.in_keys, strict=False).to(device)
    held_out = held_out.select(*loss_fn.in_keys, strict=False).to(device) if held_out is not None else None
    optim = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)

    m = train.batch_size[0]
    buffer = None
    if m > batch_size:
        buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(m, device=device), sampler=RandomSampler(),
            batch_size=batch_size, generator=torch.Generator().manual_seed(seed),
        )
        buffer.extend(train)

    history: list[dict[str, float]] = []
    result: dict[str, Any] = {"steps": steps, "num_train": m,
                              "num_eval": 0 if held_out is None else held_out.batch_size[0]}
    bar = tqdm(range(1, steps + 1), desc="score model", disable=not progress)
    for step in bar:
        batch = train if buffer is None else buffer.sample().exclude("index")
        out = loss_fn(batch)
        loss = out["loss_preference"]
        if not bool(torch.isfinite(loss)):
            raise FloatingPointError(
                f"train_score_model: non-finite loss at step {step} (scores NaN/inf; lower lr or check inputs)"
            )
        optim.zero_grad(set_to_none=True)
        loss.backward()
        if max_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_(model.parameters(), max_grad_norm)
        optim.step()
        if step % eval_interval == 0 or step == steps:
            record = {"step": float(step), "train_loss": float(loss.detach())}
            if math.isfinite(float(out["accuracy"])):
                record["train_accuracy"] = float(out["accuracy"])
            if held_out is not None:
                ev = _evaluate(loss_fn, held_out)
                record["eval_loss"] = ev["loss"]
                if "accuracy" in ev:
                    record["eval_accuracy"] = ev["accuracy"]
            history.append(record)
            bar.set_postfix({k: round(v, 4) for k, v in record.items() if k != "step"})
            if logger is not None:
                for key, value in record.items():
                    if key != "step" and math.isfinite(value):
                        logger.log_scalar(f"{log_prefix}{key}", value, step=step)
    final = _evaluate(loss_fn, train)
    result["train_loss"] = final["loss"]
    if "accuracy" in final:
        result["train_accuracy"] = final["accuracy"]
    if held_out is not None:
        ev = _evaluate(loss_fn, held_out)
        result["eval_loss"] = ev["loss"]
        if "accuracy" in ev:
            result["eval_accuracy"] = ev["accuracy"]
    result["history"] = history
    return result
