"""Which pairs to label: uniform (the paper) or active query selection.

With a budget of 30 full-trajectory labels, uniformly drawn pairs mostly teach the order of a
dataset's behaviour groups and little of the order inside them (BENCHMARKS.md, score model).
Active query selection (PEBBLE, Lee et al. 2021; OPRL, Shin et al. 2023) spends the budget in
rounds: label ``initial`` uniform pairs, fit a provisional score model, ask the scripted teacher
about the ``per_round`` pairs that model is least sure of, refit, and so on until ``num_pairs``.

Strategies (:data:`QUERY_STRATEGIES`), each a priority over candidate pairs ``(i, j)`` with
``p_c = sigmoid(s_c(tau_j) - s_c(tau_i))`` for ensemble member ``c``:

* ``"random"``: uniform pairs, no model (:func:`~torchrl_ftb.data.labels.make_scripted_labels`,
  the paper's protocol and the default everywhere);
* ``"entropy"``: one model; ask where ``|p - 0.5|`` is smallest (the most uncertain prediction);
* ``"disagreement"``: a ``members``-member ensemble; ask where ``std_c p_c`` is largest.

Only a scripted teacher can be asked again; fixed label files (PT format) are what they are.
The final score model is trained on the returned labels as usual, so switching strategies
changes only which pairs are labelled.

Example:
    >>> from torchrl_ftb.data.labels import ReturnTeacher
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=12, horizon=8, seed=0)
    >>> labels = make_query_labels(trajs, num_pairs=6, teacher=ReturnTeacher(), seed=0,
    ...                            strategy="entropy", initial=4, per_round=2, steps=5,
    ...                            model_kwargs={"num_cells": 8})
    >>> labels.batch_size
    torch.Size([6])
"""
from __future__ import annotations

from typing import Any, Mapping

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_ftb.data.labels import ReturnTeacher, draw_pairs, label_pairs, make_scripted_labels
from torchrl_ftb.preference.score import ScoreModel, score_trajectories
from torchrl_ftb.preference.train import train_score_model

__all__ = ["QUERY_STRATEGIES", "query_priority", "select_queries", "make_query_labels"]

QUERY_STRATEGIES = ("random", "entropy", "disagreement")
_LABEL_KEYS = ("tau0", "tau1", "label", "index0", "index1", "start0", "start1")


def query_priority(member_scores: torch.Tensor, index0: torch.Tensor, index1: torch.Tensor, *,
                   strategy: str) -> torch.Tensor:
    """How much labelling each candidate pair would teach (higher: ask first).

    Args:
        member_scores: ``[C, N]`` scores of every trajectory by each ensemble member.
        index0, index1: ``[P]`` candidate pairs.
        strategy: ``"entropy"`` (``-|mean_c p_c - 0.5|``) or ``"disagreement"`` (``std_c p_c``,
            needs ``C >= 2``).

    Example:
        >>> scores = torch.tensor([[0.0, 1.0, 5.0], [0.0, 3.0, 5.0]])
        >>> query_priority(scores, torch.tensor([0, 0]), torch.tensor([1, 2]), strategy="disagreement").argmax()
        tensor(0)
    """
    if member_scores.ndim != 2:
        raise ValueError(f"query_priority: member_scores must be [C, N], got {list(member_scores.shape)}")
    prob = torch.sigmoid(member_scores[:, index1] - member_scores[:, index0])  # [C, P]
    if strategy == "entropy":
        return -(prob.mean(0) - 0.5).abs()
    if strategy == "disagreement":
        if member_scores.shape[0] < 2:
            raise ValueError("query_priority: 'disagreement' needs an ensemble (member_scores with C >= 2)")
        return prob.std(0)
    raise ValueError(f"query_priority: unknown strategy {strategy!r}; choose 'entropy' or 'disagreement'")


def select_queries(member_scores: torch.Tensor, *, count: int, strategy: str,
                   asked: torch.Tensor | None = None, distinct: bool = True, max_candidates: int = 200_000,
                   seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``count`` not-yet-asked pairs ``(i, j), i < j`` of highest :func:`query_priority`.

    Candidates are all ``N(N-1)/2`` pairs, or ``max_candidates`` uniform ones when there are more.
    With ``distinct`` (default) the pairs of one call share no trajectory where the candidates
    allow: taken greedily in priority order, a pair is skipped when one of its trajectories is
    already in the batch (the best skipped pairs fill the batch when no disjoint one is left).
    Without it, one trajectory the model is unsure about fills the whole batch (on sweep-into
    every pair of a 10-pair round compared the same trajectory; BENCHMARKS #3).

    Args:
        member_scores: ``[C, N]`` member scores of every trajectory.
        count: pairs to return.
        strategy: see :func:`query_priority`; or ``"random"`` (uniform, the scores unused).
        asked: ``[A, 2]`` pairs already labelled (either order); never returned again.
        distinct: no trajectory in two of the returned pairs (where the candidates allow).
        max_candidates: cap on the candidates scored.
        seed: seeds the candidate draw when capped, and ``"random"``.

    Example:
        >>> i, j = select_queries(torch.tensor([[0.0, 0.1, 9.0]]), count=1, strategy="entropy")
        >>> (i.item(), j.item())
        (0, 1)
    """
    n = member_scores.shape[-1]
    total = n * (n - 1) // 2
    if total <= max_candidates:
        i, j = torch.triu_indices(n, n, offset=1)
    else:
        i, j = draw_pairs(n, max_candidates, seed=seed)
    if strategy == "random":
        priority = torch.rand(i.shape[0], generator=torch.Generator().manual_seed(seed))
    else:
        priority = query_priority(member_scores, i, j, strategy=strategy)
    if asked is not None and asked.numel():
        asked = asked.to(i.device)
        lo, hi = asked.min(-1).values, asked.max(-1).values
        priority = priority.masked_fill(torch.isin(i * n + j, lo * n + hi), -float("inf"))
    order = priority.argsort(descending=True, stable=True)
    order = order[torch.isfinite(priority[order])]
    if count > order.numel():
        raise ValueError(f"select_queries: asked for {count} new pairs but only {order.numel()} candidates are left")
    top = _disjoint_first(i[order], j[order], count) if distinct else torch.arange(count)
    return i[order[top]], j[order[top]]


def _disjoint_first(i: torch.Tensor, j: torch.Tensor, count: int) -> torch.Tensor:
    """Positions of ``count`` pairs, in priority order, greedily sharing no trajectory; when no
    disjoint pair is left (small datasets), the best remaining pairs fill the batch."""
    used: set[int] = set()
    keep: list[int] = []
    for pos, (a, b) in enumerate(zip(i.tolist(), j.tolist())):
        if a not in used and b not in used:
            used.update((a, b))
            keep.append(pos)
            if len(keep) == count:
                return torch.tensor(keep, dtype=torch.int64)
    chosen = set(keep)
    keep += [pos for pos in range(i.numel()) if pos not in chosen][: count - len(keep)]
    return torch.tensor(sorted(keep), dtype=torch.int64)


def make_query_labels(
    trajs: TensorDictBase,
    *,
    num_pairs: int,
    teacher: ReturnTeacher,
    seed: int,
    strategy: str = "random",
    initial: int = 10,
    per_round: int = 10,
    members: int = 3,
    distinct: bool = True,
    steps: int = 300,
    lr: float = 1e-3,
    model_kwargs: Mapping[str, Any] | None = None,
    normalize_observations: bool = True,
    device: torch.device | str | None = None,
) -> TensorDict:
    """``num_pairs`` full-trajectory labels, the pairs chosen by ``strategy`` (module docstring).

    ``"random"`` is exactly :func:`~torchrl_ftb.data.labels.make_scripted_labels`. The active
    strategies start from its first ``initial`` pairs (same seed), then add ``per_round`` pairs per
    round chosen by a provisional :class:`ScoreModel` (``members`` of them for
    ``"disagreement"``, one for ``"entropy"``; ``model_kwargs`` as for the final model, observation
    normaliser fitted on ``trajs``) trained for ``steps`` full-batch Adam steps at ``lr`` on the
    labels so far. While every label so far is a tie there is nothing to fit, and the round's pairs
    are drawn uniformly instead.

    Args:
        trajs: ``[N, H]`` trajectory batch with the keys the teacher needs.

    Keyword Args:
        num_pairs: label budget ``M``.
        teacher: the scripted teacher that is asked.
        seed: seeds the pairs, their orientation and the provisional models.
        strategy: one of :data:`QUERY_STRATEGIES`.
        initial: uniform pairs before the first round (``>= 2``).
        per_round: pairs added per round.
        members: ensemble size for ``"disagreement"`` (``>= 2``).
        distinct: a round's pairs share no trajectory (:func:`select_queries`).
        steps, lr: training of each provisional model.
        model_kwargs: :class:`ScoreModel` keyword arguments (``num_cells``, ``num_layers``,
            ``gamma``, ``reward_activation``; ``None`` values mean the default).
        normalize_observations: fit the provisional models' observation normaliser on ``trajs``.
        device: where the provisional models train.

    Returns:
        Label set ``[M]`` (``torchrl_ftb.data.labels`` layout), the first ``initial`` rows those of
        ``make_scripted_labels(trajs, num_pairs=initial, seed=seed)``.

    Raises:
        ValueError: unknown strategy, ``initial < 2``, ``per_round < 1``, ``members < 2`` with
            ``"disagreement"``, or more pairs than the dataset has.
    """
    if strategy not in QUERY_STRATEGIES:
        raise ValueError(f"make_query_labels: unknown strategy {strategy!r}; choose one of {list(QUERY_STRATEGIES)}")
    if strategy == "random" or num_pairs <= initial:
        return make_scripted_labels(trajs, num_pairs=num_pairs, teacher=teacher, seed=seed)
    if initial < 2 or per_round < 1:
        raise ValueError(f"make_query_labels: need initial >= 2 and per_round >= 1, got {initial}, {per_round}")
    if strategy == "disagreement" and members < 2:
        raise ValueError(f"make_query_labels: 'disagreement' needs members >= 2, got {members}")
    n = trajs.batch_size[0]
    if num_pairs > n * (n - 1) // 2:
        raise ValueError(f"make_query_labels: asked for {num_pairs} pairs but {n} trajectories have only "
                         f"{n * (n - 1) // 2} distinct pairs")
    labels = make_scripted_labels(trajs, num_pairs=initial, teacher=teacher, seed=seed).select(*_LABEL_KEYS)
    round_ = 0
    while labels.batch_size[0] < num_pairs:
        count = min(per_round, num_pairs - labels.batch_size[0])
        asked = torch.stack([labels["index0"], labels["index1"]], -1)
        round_seed = seed * 1000 + round_
        if bool((labels["label"] != 0.5).any()):
            scores = _provisional_scores(trajs, labels, members=members if strategy == "disagreement" else 1,
                                         seed=round_seed, steps=steps, lr=lr, model_kwargs=model_kwargs,
                                         normalize_observations=normalize_observations, device=device)
            i, j = select_queries(scores, count=count, strategy=strategy, asked=asked, distinct=distinct,
                                  seed=round_seed)
        else:  # only ties so far: no preference to fit, ask uniformly
            i, j = select_queries(torch.zeros(1, n), count=count, strategy="random", asked=asked, distinct=distinct,
                                  seed=round_seed)
        # tau0 = the lower index (the Bradley-Terry loss is symmetric in the two sides)
        new = label_pairs(trajs, i, j, teacher=teacher)
        labels = torch.cat([labels, new.select(*_LABEL_KEYS)], 0)
        round_ += 1
    labels.set_non_tensor("teacher", teacher.name)
    return labels


def _provisional_scores(trajs: TensorDictBase, labels: TensorDictBase, *, members: int, seed: int, steps: int,
                        lr: float, model_kwargs: Mapping[str, Any] | None, normalize_observations: bool,
                        device: torch.device | str | None) -> torch.Tensor:
    """``[C, N]`` member scores of a score model fitted to ``labels`` (one active round)."""
    model = ScoreModel(trajs["observation"].shape[-1], trajs["action"].shape[-1], num_members=members, seed=seed,
                       device=device, **{k: v for k, v in (model_kwargs or {}).items() if v is not None})
    if normalize_observations:
        model.fit_normalizer(trajs)
    train_score_model(model, labels.select("tau0", "tau1", "label"), steps=steps, lr=lr, eval_fraction=0.0,
                      seed=seed, progress=False, device=device)
    # what the model reads (its stop-rule fill's termination flag too, where present), nothing else
    return score_trajectories(model, trajs.select(*model.read_keys, strict=False), members=True).cpu()
