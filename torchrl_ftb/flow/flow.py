"""Flow to better: iterative trajectory improvement with a conditional diffuser (Alg. 4).

Starting from the top-``k`` dataset trajectories by score ``s_psi``, every flow step
regenerates each *current* trajectory conditioned on itself, and a sample replaces its
condition (and joins the pool) only when it is **valid** and its score **improves**:

* **valid**: finite on its valid steps; every diffused value within ``max_abs_z`` on the
  diffuser's normaliser scale (authors: 30); detected length ``>= min_length``; actions
  within ``action_limit + action_tolerance``; and, when given, ``validity_fn(samples)`` (a
  domain check, e.g. Meta-World's frame-stack consistency,
  :func:`torchrl_ftb.envs.metaworld_frame_stack_check`);
* **improves**: on the *dataset-normalised* score ``ŝ = (s - s_min) / (s_max - s_min)``
  (``s_min``/``s_max`` computed once from the dataset scores, with the score model's own
  ``gamma``: the one score definition used for blocks, filter and reports), a sample is
  accepted when ``ŝ_new > σ · ŝ_old`` (Table 6: σ = 1.1 Meta-World, 1.05 D4RL). On the
  dataset ``ŝ ∈ [0, 1]``, so this is the authors' ratio rule on their min–max normalised
  scores, but it stays meaningful when raw scores are negative (a raw ratio flips sign
  there) and it does not mix γ = 0.99 (blocks) with γ = 1 (filter) as their code does.
  For ``ŝ_old <= 0`` (only the dataset minimum) any strict increase is accepted.
  Near the top the rule asks for an absolute jump: the dataset's best trajectory (``ŝ = 1``)
  is replaced only by a sample ``(σ - 1)(s_max - s_min)`` above the dataset's max, so a max
  that sits within that margin of the best the task allows cannot rise under σ > 1.
  ``threshold=1.0`` accepts any strict gain (e.g. to ask whether the samples beat the data's
  best at all).
  With an ensemble score model, ``ensemble_rule="all"`` asks every member's own normalised
  score to improve (a pessimistic filter: a sample that exploits one member's extrapolation
  off the data is rejected); ``"mean"`` (default) uses the ensemble-mean score.

The number of flow steps is adaptive (App. B.4): ``t_flow = K - i`` with ``i`` the 1-based
block of the lowest-scored top-``k`` trajectory, optionally capped (``max_flow_steps``) and
floored (``min_flow_steps``, default 1: the authors' code silently ran 0 steps, i.e. plain
BC on the top-k, when the top-k all sat in the last block). The flow stops early when fewer
than ``early_stop_fraction`` (5 %) of the trajectories improve in a step. The final set is
the top-``k`` of the pool {original top-k} ∪ {all accepted samples}.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from tensordict.nn import TensorDictModule
    >>> from torchrl_ftb.flow import FlowToBetter
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> data = make_toy_dataset(num_trajectories=20, horizon=8, seed=0)
    >>> def better(cond):  # a stand-in sampler: push x-actions up
    ...     out = cond.select("observation", "action", "mask").clone()
    ...     out["action"][..., 0] = (out["action"][..., 0] + 0.3).clamp(-1, 1) * out["mask"]
    ...     return out
    >>> sampler = TensorDictModule(better, ["condition"], ["sample"])
    >>> flow = FlowToBetter(sampler, lambda td: td["action"][..., 0].mul(td["mask"]).sum(-1),
    ...                     top_k=5, threshold=1.0, flow_steps=2, progress=False)
    >>> result = flow(data)
    >>> result.trajectories.batch_size, bool(result.scores.mean() > result.original_scores.mean())
    (torch.Size([5, 8]), True)
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from tqdm.auto import tqdm

from torchrl_ftb.data import (
    REWARD_KEY, stop_rule_fill, success_streak_fired, success_streak_length, trajectories_to_flat, validate_trajectories,
)
from torchrl_ftb.diffusion.normalizer import TrajectoryNormalizer
from torchrl_ftb.preference import (
    ScoreModel, make_blocks, normalized_scores, score_trajectories, with_normalized_scores,
)

__all__ = [
    "FlowToBetter", "FlowResult", "adaptive_flow_steps", "check_flow_options", "clip_actions", "default_min_length", "improves",
    "masked_true_return", "masked_true_returns", "normalized_scores", "return_summary", "trajectory_validity",
    "true_return_score",
]

TRAJ_KEYS = ("observation", "action", "mask")


def improves(new_hat: torch.Tensor, old_hat: torch.Tensor, threshold: float) -> torch.Tensor:
    """Acceptance rule on normalised scores: ``ŝ_new > σ ŝ_old`` (``ŝ_new > ŝ_old`` if ``ŝ_old <= 0``)."""
    return torch.where(old_hat > 0, new_hat > threshold * old_hat, new_hat > old_hat)


def adaptive_flow_steps(block_ids: torch.Tensor, top_indices: torch.Tensor, scores: torch.Tensor) -> int:
    """``t_flow = K - i`` with ``i`` the 1-based block of the lowest-scored top-k trajectory.

    ``K`` is the number of blocks actually present (``block_ids.max() + 1``; ids are 0-based).

    Example:
        >>> ids = torch.tensor([0, 0, 1, 1, 2, 2, 3, 3])
        >>> adaptive_flow_steps(ids, torch.tensor([7, 6, 5]), torch.arange(8.0))  # worst: id 2 -> i=3
        1
    """
    block_ids = torch.as_tensor(block_ids)
    if block_ids.shape != scores.shape:
        raise ValueError(f"adaptive_flow_steps: block_ids {list(block_ids.shape)} != scores {list(scores.shape)}")
    worst = top_indices[scores[top_indices].argmin()]
    num_blocks = int(block_ids.max()) + 1
    return num_blocks - (int(block_ids[worst]) + 1)


def trajectory_validity(
    samples: TensorDictBase,
    *,
    normalizer: Any | None,
    max_abs_z: float = 30.0,
    min_length: int = 1,
    action_limit: float = 1.0,
    action_tolerance: float = 0.5,
) -> dict[str, torch.Tensor]:
    """Per-trajectory validity checks of generated trajectories ``[N, H]`` (bool ``[N]`` each).

    Returns ``{"finite", "in_bounds", "long_enough", "actions_ok", "valid"}``. ``in_bounds``
    uses ``normalizer.normalize`` on ``[observation, action]`` (plus ``("next", "reward")`` if
    the normaliser's dimension asks for it); all True if ``normalizer`` is None.
    """
    mask = samples.get("mask").bool()
    obs, act = samples.get("observation"), samples.get("action")
    m3 = mask[..., None]
    finite = torch.where(m3, torch.isfinite(obs), True).all(-1).all(-1) & torch.where(
        m3, torch.isfinite(act), True
    ).all(-1).all(-1)
    if REWARD_KEY in samples.keys(True):
        finite &= torch.where(m3, torch.isfinite(samples.get(REWARD_KEY)), True).all(-1).all(-1)
    if normalizer is not None:
        x = torch.cat([obs, act], -1)
        dim = getattr(normalizer, "dim", x.shape[-1])
        if dim == x.shape[-1] + 1 and REWARD_KEY in samples.keys(True):
            x = torch.cat([x, samples.get(REWARD_KEY)], -1)
        if dim != x.shape[-1]:
            raise ValueError(
                f"trajectory_validity: normaliser dimension {dim} does not match the sample's "
                f"observation+action dimension {x.shape[-1]}"
            )
        z = normalizer.normalize(torch.nan_to_num(x.to(normalizer.mean.device), nan=0.0, posinf=0.0, neginf=0.0))
        in_bounds = torch.where(m3.to(z.device), z.abs() < max_abs_z, True).all(-1).all(-1).to(mask.device)
    else:
        in_bounds = torch.ones_like(finite)
    long_enough = mask.sum(-1) >= min_length
    actions_ok = torch.where(m3, act.abs() <= action_limit + action_tolerance, True).all(-1).all(-1)
    valid = finite & in_bounds & long_enough & actions_ok
    return {"finite": finite, "in_bounds": in_bounds, "long_enough": long_enough, "actions_ok": actions_ok,
            "valid": valid}


def clip_actions(trajs: TensorDictBase, action_limit: float) -> TensorDictBase:
    """Clip the ``action`` of generated trajectories to ``[-action_limit, action_limit]`` and zero
    it on padded steps, in place (what a valid sample's small overshoot becomes); returns ``trajs``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"action": torch.tensor([[[1.2], [0.5]]]), "mask": torch.tensor([[True, False]])}, [1, 2])
        >>> clip_actions(td, 1.0)["action"].flatten().tolist()
        [1.0, 0.0]
    """
    trajs.set("action", trajs.get("action").clamp(-action_limit, action_limit) * trajs.get("mask")[..., None])
    return trajs


def default_min_length(trajs: TensorDictBase) -> int:
    """Validity's default shortest generated length: half the shortest of ``trajs``, at least 2."""
    return max(2, int(trajs.get("mask").sum(-1).min()) // 2)


def masked_true_returns(
    trajs: TensorDictBase,
    true_reward_fn: Callable,
    *,
    horizons: tuple[int | None, ...] = (None,),
    streaks: tuple[int | None, ...] | None = None,
) -> torch.Tensor:
    """True returns of each trajectory under one or more definitions, ``float64 [N, len(horizons)]``.

    ``true_reward_fn(observation [L, obs], action [L, act]) -> reward [L] or [L, 1]`` is
    called once per trajectory on its valid prefix only (simulator-based reward functions,
    e.g. Meta-World's, then never see padding), and every definition is read off that one call.
    A ``None`` horizon is the undiscounted sum over the valid steps; an integer ``horizon`` is
    the stop-rule fill of :func:`torchrl_ftb.data.labels.true_return`: a trajectory of ``n <
    horizon`` steps keeps earning its last step's reward up to ``horizon`` steps (on Meta-World a
    success ends the episode, so a faster success earns more). Generated trajectories carry no
    termination flag, so the fill is only meaningful on tasks without terminal states.

    ``streaks`` (one entry per horizon, ``None``: no cut) first cuts each trajectory where a
    stop rule of that many consecutive successes would have ended it
    (:func:`~torchrl_ftb.data.success_streak_length`): recorded episodes were cut there,
    generated ones were not. Such a column fills only the trajectories that rule ended: a recorded
    episode ends by it or by the time limit, while a generated one may end early with no streak (where
    the diffuser's padding starts); filling that one would pay a failure as if it had succeeded, so it
    earns its own steps only (:func:`~torchrl_ftb.data.success_streak_fired`). It needs a
    ``true_reward_fn`` that returns ``(reward, success)`` (e.g.
    ``torchrl_ftb.envs.true_reward_fn(task, with_success=True)``).

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset, toy_reward
        >>> data = make_toy_dataset(num_trajectories=3, horizon=5, seed=0)
        >>> masked_true_returns(data, toy_reward, horizons=(None, 10)).shape
        torch.Size([3, 2])
    """
    if any(h is not None and h < 1 for h in horizons):
        raise ValueError(f"masked_true_returns: every horizon must be None or >= 1, got {horizons}")
    streaks = (None,) * len(horizons) if streaks is None else tuple(streaks)
    if len(streaks) != len(horizons) or any(k is not None and k < 1 for k in streaks):
        raise ValueError(f"masked_true_returns: streaks needs one entry (None or >= 1) per horizon, got "
                         f"{streaks} for horizons {horizons}")
    need_success = any(k is not None for k in streaks)
    mask = trajs.get("mask")
    obs, act = trajs.get("observation"), trajs.get("action")
    reward = torch.zeros(mask.shape, dtype=torch.float64)
    success = torch.zeros(mask.shape, dtype=torch.bool)
    for i, n in enumerate(mask.sum(-1).tolist()):
        if not n:
            continue
        out = true_reward_fn(obs[i, :n], act[i, :n])
        if isinstance(out, tuple):
            out, succ = out
            success[i, :n] = torch.as_tensor(succ).reshape(-1).bool().cpu()
        elif need_success:
            raise ValueError("masked_true_returns: streaks= needs a true_reward_fn that returns (reward, success), "
                             f"got one that returns {type(out).__name__}")
        reward[i, :n] = torch.as_tensor(out).double().reshape(-1).cpu()
    mask = mask.cpu()
    position = torch.arange(mask.shape[-1])
    cols = []
    for horizon, streak in zip(horizons, streaks):
        m, unfilled = mask, None
        if streak is not None:  # cut where the rule fires; no fill where it never does (not a stop-rule end)
            m = mask & (position < success_streak_length(success, mask, streak=streak)[:, None])
            unfilled = (~success_streak_fired(success, mask, streak=streak))[:, None].expand_as(m)
        ret = (reward * m).sum(-1)
        if horizon is not None:  # the one fill definition (stop_rule_fill), in float64
            last, weight = stop_rule_fill(m, horizon=horizon, terminated=unfilled)
            ret = ret + weight * reward.gather(-1, last[:, None]).squeeze(-1)
        cols.append(ret)
    return torch.stack(cols, -1) if cols else torch.zeros(mask.shape[0], 0, dtype=torch.float64)


def masked_true_return(trajs: TensorDictBase, true_reward_fn: Callable, *, horizon: int | None = None) -> torch.Tensor:
    """True return ``sum_h r(s_h, a_h)`` over the valid steps of each trajectory, ``float64 [N]``.

    ``horizon``: the stop-rule fill (see :func:`masked_true_returns`); ``None`` (default) is the
    paper's plain sum.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset, toy_reward
        >>> data = make_toy_dataset(num_trajectories=3, horizon=5, seed=0)
        >>> ret = masked_true_return(data, toy_reward)
        >>> bool(torch.allclose(ret.float(), data["next", "reward"].squeeze(-1).sum(-1), atol=1e-5))
        True
    """
    return masked_true_returns(trajs, true_reward_fn, horizons=(horizon,))[:, 0]


def true_return_score(
    true_reward_fn: Callable, *, horizon: int | None = None, streak: int | None = None
) -> Callable[[TensorDictBase], torch.Tensor]:
    """An oracle ``score_model`` for :class:`FlowToBetter`: each trajectory's true return.

    The flow then picks its top-k, accepts samples and ranks the final set by the ground truth
    instead of ``s_psi`` (the same ratio rule on the dataset-normalised return). This is an
    analysis tool, not preference-based RL: it bounds what the diffuser's samples allow when
    the filter makes no mistake. ``horizon`` / ``streak``: the return definition of
    :func:`masked_true_returns` (one column).

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset, toy_reward
        >>> data = make_toy_dataset(num_trajectories=3, horizon=5, seed=0)
        >>> score = true_return_score(toy_reward)
        >>> bool(torch.allclose(score(data), masked_true_return(data, toy_reward)))
        True
    """
    horizons, streaks = (horizon,), (streak,)

    def score(trajs: TensorDictBase) -> torch.Tensor:
        return masked_true_returns(trajs, true_reward_fn, horizons=horizons, streaks=streaks)[:, 0]

    return score


def return_summary(before: torch.Tensor, after: torch.Tensor, *, prefix: str = "true_return") -> dict[str, float]:
    """``{prefix}_{mean,max}_{before,after}`` of two sets of returns or scores (the improvement statistics).

    Example:
        >>> return_summary(torch.tensor([1.0, 3.0]), torch.tensor([2.0, 4.0]))["true_return_mean_after"]
        3.0
    """
    return {f"{prefix}_mean_before": float(before.mean()), f"{prefix}_max_before": float(before.max()),
            f"{prefix}_mean_after": float(after.mean()), f"{prefix}_max_after": float(after.max())}


def accepted_gain_stats(gain: torch.Tensor, names: list[str]) -> dict[str, float]:
    """Mean and positive share of the accepted samples' true-return gains over what they replaced.

    ``gain`` is ``[M, D]``, one column per return definition in ``names``. The first column (the
    plain sum) keeps its historical keys ``accepted_true_gain_{mean,positive}``; the others are
    ``accepted_<name>_gain_{mean,positive}`` (on Meta-World the plain sum pays length, so a sample
    that turns a fast success into a 500-step one shows a plain gain and a stop-rule loss).

    Example:
        >>> stats = accepted_gain_stats(torch.tensor([[2.0, -1.0], [4.0, 3.0]]), ["true_return", "true_return_filled"])
        >>> stats["accepted_true_gain_mean"], stats["accepted_true_return_filled_gain_positive"]
        (3.0, 0.5)
    """
    out: dict[str, float] = {}
    for j, name in enumerate(names):
        key = "accepted_true_gain" if j == 0 else f"accepted_{name}_gain"
        out[f"{key}_mean"] = float(gain[:, j].mean())
        out[f"{key}_positive"] = float((gain[:, j] > 0).double().mean())
    return out


@dataclass
class FlowResult:
    """Output of :class:`FlowToBetter`.

    Attributes:
        trajectories: the improved set, ``[k, H]`` with ``observation``, ``action``, ``mask``
            (and ``("next", "reward")`` with ``keep_reward``).
        scores: their scores ``s_psi`` ``[k]``.
        source_step: flow step that produced each final trajectory ``[k]`` (0: original).
        original: the starting top-k ``[k, H]`` (same keys); ``original_scores`` ``[k]``.
        generated: every accepted sample, ``[M, H]`` (``M`` may be 0), with ``generated_step``.
        stats: one dict per flow step (accept/valid rates, mean/max score, mean/max true return).
        summary: scalars (flow steps planned/run, s_min/s_max, before/after means, ...).
        original_indices: dataset indices of the starting top-k.
        true_returns, original_true_returns: ``[k]`` true returns (``true_reward_fn`` given) or None.
        filled_true_returns, original_filled_true_returns: ``[k]`` true returns with the stop-rule
            fill (``true_return_horizon`` given) or None.
    """

    trajectories: TensorDict
    scores: torch.Tensor
    source_step: torch.Tensor
    original: TensorDict
    original_scores: torch.Tensor
    original_indices: torch.Tensor
    generated: TensorDict
    generated_step: torch.Tensor
    stats: list[dict[str, float]] = field(default_factory=list)
    summary: dict[str, float] = field(default_factory=dict)
    true_returns: torch.Tensor | None = None
    original_true_returns: torch.Tensor | None = None
    filled_true_returns: torch.Tensor | None = None
    original_filled_true_returns: torch.Tensor | None = None

    def __iter__(self) -> Iterator[Any]:
        """``improved, stats = flow(data)``."""
        return iter((self.trajectories, self.stats))


def check_flow_options(*, top_k: int, threshold: float = 1.1, num_blocks: int | None = None,
                       flow_steps: int | None = None, max_flow_steps: int | None = None, min_flow_steps: int = 1,
                       early_stop_fraction: float = 0.05, max_abs_z: float = 30.0, min_length: int | None = None,
                       action_tolerance: float = 0.5, candidates: int = 1, batch_size: int = 256,
                       ensemble_rule: str = "mean", num_members: int = 1) -> None:
    """Check :class:`FlowToBetter`'s scalar options (same names and defaults) without building it.

    A recipe calls it before any training, so a bad flow option fails in seconds instead of after the
    diffuser's training; :class:`FlowToBetter` calls it too. ``num_members``: the score model's
    ensemble size (``ensemble_rule="all"`` needs at least 2).

    Raises:
        ValueError: naming the first option out of range.

    Example:
        >>> check_flow_options(top_k=100, threshold=1.1, num_blocks=5)
        >>> check_flow_options(top_k=0)
        Traceback (most recent call last):
        ...
        ValueError: FlowToBetter: top_k must be >= 1, got 0
    """
    if top_k < 1:
        raise ValueError(f"FlowToBetter: top_k must be >= 1, got {top_k}")
    if not threshold >= 1.0:
        raise ValueError(f"FlowToBetter: threshold σ must be >= 1 (a ratio), got {threshold}")
    if flow_steps is None and num_blocks is None:
        raise ValueError("FlowToBetter: give num_blocks (adaptive flow steps) or a fixed flow_steps")
    if num_blocks is not None and num_blocks < 1:
        raise ValueError(f"FlowToBetter: num_blocks must be >= 1, got {num_blocks}")
    if flow_steps is not None and flow_steps < 0:
        raise ValueError(f"FlowToBetter: flow_steps must be >= 0, got {flow_steps}")
    if min_flow_steps < 0 or (max_flow_steps is not None and max_flow_steps < min_flow_steps):
        raise ValueError(f"FlowToBetter: need 0 <= min_flow_steps <= max_flow_steps, got {min_flow_steps}, {max_flow_steps}")
    if not 0.0 <= early_stop_fraction <= 1.0:
        raise ValueError(f"FlowToBetter: early_stop_fraction must be in [0, 1], got {early_stop_fraction}")
    if not max_abs_z > 0:
        raise ValueError(f"FlowToBetter: max_abs_z must be > 0, got {max_abs_z}")
    if not action_tolerance >= 0:
        raise ValueError(f"FlowToBetter: action_tolerance must be >= 0, got {action_tolerance}")
    if min_length is not None and min_length < 1:
        raise ValueError(f"FlowToBetter: min_length must be >= 1 (or None), got {min_length}")
    if candidates < 1:
        raise ValueError(f"FlowToBetter: candidates must be >= 1, got {candidates}")
    if batch_size < 1:
        raise ValueError(f"FlowToBetter: batch_size must be >= 1, got {batch_size}")
    if ensemble_rule not in ("mean", "all"):
        raise ValueError(f"FlowToBetter: ensemble_rule must be 'mean' or 'all', got {ensemble_rule!r}")
    if ensemble_rule == "all" and num_members < 2:
        raise ValueError("FlowToBetter: ensemble_rule='all' needs a ScoreModel ensemble (num_members >= 2)")


class FlowToBetter(nn.Module):
    """Flow to better (Alg. 4) as a TorchRL component around a sampler and a score model.

    Args:
        sampler: ``TensorDictModule`` ``"condition"`` ``[B, H]`` → ``"sample"`` ``[B, H]``
            (``observation``, ``action``, ``mask``), e.g. ``torchrl_ftb.diffusion.DiffusionSampler``.
        score_model: :class:`~torchrl_ftb.preference.ScoreModel` (or any callable mapping an
            ``[N, H]`` batch to ``[N]`` scores).

    Keyword Args:
        top_k: trajectories to improve (Table 6: 100 Meta-World, 300 D4RL).
        threshold: σ of the acceptance rule on normalised scores (module docstring).
        num_blocks: K for :func:`~torchrl_ftb.preference.make_blocks` when block ids are not
            passed to :meth:`forward` (ignored if ``flow_steps`` is given).
        flow_steps: fixed number of flow steps (``None``: adaptive ``K - i``).
        max_flow_steps: cap on the adaptive count; ``min_flow_steps``: floor (default 1).
        early_stop_fraction: stop when fewer than this fraction improve in a step (0.05).
        max_abs_z, min_length, action_limit, action_tolerance: validity (see
            :func:`trajectory_validity`); ``min_length=None`` uses half the shortest start
            trajectory (at least 2).
        validity_fn: optional extra validity, ``[N, H]`` samples -> ``[N]`` bool (True: valid),
            ANDed with :func:`trajectory_validity`; its share is logged as ``domain_valid_rate``.
        normalizer: object with ``normalize(x)`` for the |z| check; default the sampler's
            ``normalizer`` attribute, else a z-score fitted on the dataset's valid steps.
        true_reward_fn: ``(observation, action) -> reward`` ground truth, for statistics only.
        true_return_horizon: also report the true return with the stop-rule fill over this many
            steps (:func:`masked_true_returns`; ``true_return_filled_*`` statistics), e.g. 500 on
            Meta-World, where a success ends the episode and the plain sum pays a slow success
            more than a fast one. ``None`` (default): the plain sum only.
        true_return_streak: with ``true_return_horizon``, also report the fill after cutting each
            trajectory where a stop rule of this many consecutive successes would have ended it
            (``true_return_filled_stop_rule_*``; 25 on our Meta-World data, whose episodes were
            cut so, while samples are not); a sample that ends early with no such streak gets no
            fill there. Needs a ``true_reward_fn`` returning ``(reward, success)``. ``None``
            (default): no such column.
        candidates: samples drawn per condition in each flow step; the valid one the score model
            ranks highest is the step's proposal (best-of-n). 1 (default): Alg. 4's single sample.
            The score model is the filter either way, so more candidates trade sampling time
            (n×) for more proposals that clear σ; ``valid_rate`` is then the share of conditions
            with at least one valid candidate, ``candidate_valid_rate`` the share of candidates.
        batch_size: trajectories per sampler call (memory bound).
        seed: seeds the sampler noise (global RNG inside a fork).
        ensemble_rule: ``"mean"`` (accept on the ensemble-mean score) or ``"all"`` (every
            member's normalised score must improve; needs a :class:`ScoreModel` ensemble). The
            final top-k is ranked by the mean score either way.
        keep_reward: carry ``("next", "reward")`` through the flow: the data must have it, the
            sampler must generate it (a diffuser with ``reward_channel=True``), and the result's
            trajectories hold it (FTB as data augmentation, :mod:`torchrl_ftb.augmentation`).
        logger: torchrl logger (``log_scalar``), optional; ``progress``: tqdm bar.
    """

    def __init__(
        self,
        sampler: Callable[[TensorDictBase], TensorDictBase],
        score_model: ScoreModel | Callable[[TensorDictBase], torch.Tensor],
        *,
        top_k: int,
        threshold: float = 1.1,
        num_blocks: int | None = None,
        flow_steps: int | None = None,
        max_flow_steps: int | None = None,
        min_flow_steps: int = 1,
        early_stop_fraction: float = 0.05,
        max_abs_z: float = 30.0,
        min_length: int | None = None,
        action_limit: float = 1.0,
        action_tolerance: float = 0.5,
        validity_fn: Callable[[TensorDictBase], torch.Tensor] | None = None,
        normalizer: Any | None = None,
        true_reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
        true_return_horizon: int | None = None,
        true_return_streak: int | None = None,
        candidates: int = 1,
        batch_size: int = 256,
        seed: int = 0,
        ensemble_rule: str = "mean",
        keep_reward: bool = False,
        logger: Any | None = None,
        progress: bool = True,
    ) -> None:
        super().__init__()
        check_flow_options(top_k=top_k, threshold=threshold, num_blocks=num_blocks, flow_steps=flow_steps,
                           max_flow_steps=max_flow_steps, min_flow_steps=min_flow_steps,
                           early_stop_fraction=early_stop_fraction, max_abs_z=max_abs_z, min_length=min_length,
                           action_tolerance=action_tolerance, candidates=candidates, batch_size=batch_size,
                           ensemble_rule=ensemble_rule, num_members=getattr(score_model, "num_members", 1))
        if true_return_horizon is not None and (true_reward_fn is None or true_return_horizon < 1):
            raise ValueError("FlowToBetter: true_return_horizon needs a true_reward_fn and must be >= 1, got "
                             f"{true_return_horizon}")
        if true_return_streak is not None and (true_return_horizon is None or true_return_streak < 1):
            raise ValueError("FlowToBetter: true_return_streak needs a true_return_horizon and must be >= 1, got "
                             f"{true_return_streak}")
        self.sampler = sampler
        self.score_model = score_model
        self.top_k = int(top_k)
        self.threshold = float(threshold)
        self.num_blocks = num_blocks
        self.flow_steps = flow_steps
        self.max_flow_steps = max_flow_steps
        self.min_flow_steps = int(min_flow_steps)
        self.early_stop_fraction = float(early_stop_fraction)
        self.max_abs_z = float(max_abs_z)
        self.min_length = min_length
        self.action_limit = float(action_limit)
        self.action_tolerance = float(action_tolerance)
        self.validity_fn = validity_fn
        self.normalizer = normalizer
        self.true_reward_fn = true_reward_fn
        self.true_return_horizon = true_return_horizon
        self.true_return_streak = true_return_streak
        # (statistics name, horizon, streak) of each true-return column: the plain sum, the fill when
        # asked for, and the fill after the stop-rule cut when asked for
        self._true_columns = (("true_return", None, None),)
        if true_return_horizon is not None:
            self._true_columns += (("true_return_filled", int(true_return_horizon), None),)
            if true_return_streak is not None:
                self._true_columns += (("true_return_filled_stop_rule", int(true_return_horizon),
                                        int(true_return_streak)),)
        self.candidates = int(candidates)
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.ensemble_rule = ensemble_rule
        self.keep_reward = bool(keep_reward)
        self.keys = (*TRAJ_KEYS, REWARD_KEY) if self.keep_reward else TRAJ_KEYS
        self.logger = logger
        self.progress = progress

    # -- pieces ---------------------------------------------------------------------------
    def score(self, trajs: TensorDictBase, *, members: bool = False) -> torch.Tensor:
        """Scores ``[N]`` of an ``[N, H]`` batch (no gradients); ``[C, N]`` per member if ``members``."""
        if isinstance(self.score_model, ScoreModel):
            return score_trajectories(self.score_model, trajs, batch_size=max(self.batch_size, 1024),
                                      members=members)
        with torch.no_grad():
            out = torch.as_tensor(self.score_model(trajs)).reshape(trajs.batch_size[0])
        return out[None] if members else out

    def _scores(self, trajs: TensorDictBase, mean: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mean [N], filter [C, N])`` float64 on CPU: the score and what the acceptance rule
        compares (``[1, N]``, the mean, unless ``ensemble_rule="all"``: every member's score).
        The score model runs once; ``mean`` given (e.g. the blocks' scores) is used as is."""
        if self.ensemble_rule == "all":
            members = self.score(trajs, members=True).to(torch.float64).cpu()
            return (members.mean(0) if mean is None else mean.to(torch.float64).cpu()), members
        mean = (self.score(trajs) if mean is None else mean).to(torch.float64).cpu()
        return mean, mean[None]

    @torch.no_grad()
    def generate(self, conditions: TensorDictBase) -> TensorDict:
        """One flow step's samples ``[N, H]`` conditioned on ``conditions`` (chunked)."""
        n = conditions.batch_size[0]
        params = list(self.sampler.parameters()) if isinstance(self.sampler, nn.Module) else []
        device = params[0].device if params else conditions.device
        # where the samples go back to: the conditions' device (a TensorDict without one, e.g. the toy data: its
        # tensors'), so a sampler on another device never mixes devices in the flow
        home = conditions.device if conditions.device is not None else conditions.get("mask").device
        chunks = []
        for i in range(0, n, self.batch_size):
            cond = conditions[i : i + self.batch_size].to(device)
            out = self.sampler(TensorDict({"condition": cond}, batch_size=cond.batch_size[:1]))
            sample = out.get("sample")
            if sample.batch_size != cond.batch_size:
                raise ValueError(
                    f"FlowToBetter: sampler returned 'sample' of batch_size {list(sample.batch_size)}, "
                    f"expected {list(cond.batch_size)}"
                )
            keys = [k for k in TRAJ_KEYS if k in sample.keys()]
            if len(keys) != len(TRAJ_KEYS):
                raise ValueError(f"FlowToBetter: sampler output 'sample' lacks {set(TRAJ_KEYS) - set(keys)}")
            if self.keep_reward and REWARD_KEY not in sample.keys(True):
                raise ValueError("FlowToBetter(keep_reward=True): the sampler's 'sample' has no ('next', 'reward'); "
                                 "use a diffuser with reward_channel=True")
            extra = [REWARD_KEY] if REWARD_KEY in sample.keys(True) else []
            chunks.append(sample.select(*TRAJ_KEYS, *extra).to(home))
        out = torch.cat(chunks, 0)
        out.set("mask", out.get("mask").bool())
        return out

    def propose(
        self, conditions: TensorDictBase, *, normalizer: Any, min_length: int
    ) -> tuple[TensorDict, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None, dict[str, float]]:
        """One flow step's proposals for ``conditions`` ``[N, H]``: draws ``candidates`` samples per
        condition and keeps, per condition, the valid one with the highest (mean) score.

        The action limit is checked on the raw samples (:func:`trajectory_validity`'s tolerance); the rest, the
        domain check and the score, read the samples with actions clipped (:func:`clip_actions`), which is what
        an accepted sample is kept as.

        Returns:
            ``(samples [N, H], scores [N], filter scores [C, N], valid [N], domain_valid [N] | None,
            extra statistics)``; a condition with no valid candidate gets an invalid one.
        """
        n = conditions.batch_size[0]
        samples = self.generate(conditions if self.candidates == 1 else torch.cat([conditions] * self.candidates, 0))
        valid = trajectory_validity(
            samples, normalizer=normalizer, max_abs_z=self.max_abs_z, min_length=min_length,
            action_limit=self.action_limit, action_tolerance=self.action_tolerance,
        )["valid"].cpu()
        samples = clip_actions(samples, self.action_limit)
        scores, members = self._scores(samples)
        domain_valid = None
        if self.validity_fn is not None:
            domain_valid = torch.as_tensor(self.validity_fn(samples)).bool().cpu()
            if domain_valid.shape != valid.shape:
                raise ValueError(f"FlowToBetter: validity_fn returned shape {list(domain_valid.shape)}, "
                                 f"expected {list(valid.shape)} (one bool per sample)")
            valid = valid & domain_valid
        if self.candidates == 1:
            return samples, scores, members, valid, domain_valid, {}
        extra = {"candidate_valid_rate": float(valid.double().mean())}
        rank = torch.where(valid & torch.isfinite(scores), scores, torch.full_like(scores, -math.inf))
        pick = rank.view(self.candidates, n).argmax(0) * n + torch.arange(n)  # row 0 when none is valid
        return (samples[pick], scores[pick], members[:, pick], valid[pick],
                None if domain_valid is None else domain_valid[pick], extra)

    def _resolve_normalizer(self, data: TensorDictBase):
        norm = self.normalizer if self.normalizer is not None else getattr(self.sampler, "normalizer", None)
        if norm is None:  # with keep_reward the generated reward is range-checked too (validity's +1 dimension)
            parts = [data.get("observation"), data.get("action")] + ([data.get(REWARD_KEY)] if self.keep_reward else [])
            x = torch.cat(parts, -1)
            norm = TrajectoryNormalizer(x.shape[-1]).fit(x, data.get("mask"))
        return norm

    def _planned_steps(self, block_ids, top_idx, scores) -> tuple[int, int | None]:
        if self.flow_steps is not None:
            return int(self.flow_steps), None
        adaptive = adaptive_flow_steps(block_ids, top_idx, scores)
        steps = adaptive
        if steps < self.min_flow_steps:
            warnings.warn(
                f"FlowToBetter: adaptive flow steps K - i = {adaptive} (the lowest top-{self.top_k} "
                f"trajectory is in block {int(block_ids[top_idx[scores[top_idx].argmin()]]) + 1} of "
                f"{int(block_ids.max()) + 1}); using min_flow_steps={self.min_flow_steps}",
                stacklevel=3,
            )
            steps = self.min_flow_steps
        if self.max_flow_steps is not None:
            steps = min(steps, self.max_flow_steps)
        return steps, adaptive

    def _true_return(self, trajs: TensorDictBase) -> torch.Tensor | None:
        """``[N, D]`` true returns, one column per entry of ``_true_columns`` (one oracle pass)."""
        if self.true_reward_fn is None:
            return None
        return masked_true_returns(trajs, self.true_reward_fn, horizons=tuple(h for _, h, _ in self._true_columns),
                                   streaks=tuple(k for _, _, k in self._true_columns))

    # -- main -----------------------------------------------------------------------------
    def forward(
        self,
        data: TensorDictBase,
        *,
        scores: torch.Tensor | None = None,
        block_ids: torch.Tensor | None = None,
    ) -> FlowResult:
        """Run the flow on a dataset ``[N, H]``.

        Args:
            data: the (unlabelled) dataset trajectories.
            scores: their scores ``[N]`` (computed with the score model if omitted).
            block_ids: their blocks ``[N]`` (``make_blocks(scores, num_blocks)`` if omitted).

        Returns:
            A :class:`FlowResult`.
        """
        validate_trajectories(data, name="FlowToBetter: data", require=[REWARD_KEY] if self.keep_reward else ())
        n = data.batch_size[0]
        if self.top_k > n:
            raise ValueError(f"FlowToBetter: top_k={self.top_k} exceeds the {n} dataset trajectories")
        data = data.select(*self.keys)
        if scores is not None:
            scores = torch.as_tensor(scores).reshape(-1)
            if scores.shape != (n,):
                raise ValueError(f"FlowToBetter: scores have shape {list(scores.shape)}, expected [{n}]")
        scores, member_scores = self._scores(data, scores)  # [N] and [C, N]: what the rule compares
        if not bool(torch.isfinite(member_scores).all()):
            bad = (~torch.isfinite(member_scores)).any(0).nonzero().flatten().tolist()
            raise ValueError(f"FlowToBetter: {len(bad)} dataset scores are NaN or infinite (trajectories "
                             f"{bad[:10]}); check the score model or the scores passed")
        if block_ids is None and self.flow_steps is None:
            block_ids = make_blocks(scores, self.num_blocks, seed=self.seed)
        s_min, s_max = float(scores.min()), float(scores.max())
        top_idx = scores.argsort(descending=True)[: self.top_k]
        m_min, m_max = member_scores.min(1, keepdim=True).values, member_scores.max(1, keepdim=True).values
        if not bool((m_max > m_min).all()):
            raise ValueError("FlowToBetter: every (member's) dataset score is equal; nothing to improve on")
        steps, adaptive = self._planned_steps(
            None if block_ids is None else torch.as_tensor(block_ids).cpu(), top_idx, scores
        )
        normalizer = self._resolve_normalizer(data)
        original = data[top_idx].clone()
        min_length = self.min_length
        if min_length is None:
            min_length = default_min_length(original)

        current = original.clone()
        cur_scores = scores[top_idx].clone()
        cur_members = member_scores[:, top_idx].clone()
        pool, pool_scores, pool_steps = [], [], []
        stats: list[dict[str, float]] = []
        true0 = self._true_return(original)
        cur_true = None if true0 is None else true0.clone()
        pool_true: list[torch.Tensor] = []
        bar = tqdm(range(1, steps + 1), desc="flow", disable=not self.progress)
        # the flow's own seed for every device's generator (a sampler on CUDA draws there), restored after
        with torch.random.fork_rng(devices=list(range(torch.cuda.device_count()))):
            torch.manual_seed(self.seed)
            for step in bar:
                # the conditions' normalised scores go along for samplers that read them (score_condition)
                samples, new_scores, new_members, valid, domain_valid, extra = self.propose(
                    with_normalized_scores(current, cur_scores, s_min=s_min, s_max=s_max),
                    normalizer=normalizer, min_length=min_length)
                better = improves(normalized_scores(new_members, m_min, m_max),
                                  normalized_scores(cur_members, m_min, m_max), self.threshold).all(0)
                accept = valid & better & torch.isfinite(new_scores)
                true_gain = None
                if bool(accept.any()):
                    accepted = samples[accept].select(*self.keys).clone()  # actions clipped by propose
                    if self.keep_reward:  # padding carries no reward
                        accepted.set(REWARD_KEY, accepted.get(REWARD_KEY) * accepted.get("mask")[..., None])
                    current[accept] = accepted
                    cur_scores[accept] = new_scores[accept]
                    cur_members[:, accept] = new_members[:, accept]
                    if cur_true is not None:  # only the replaced trajectories need the (costly) oracle
                        new_true = self._true_return(accepted)
                        true_gain = new_true - cur_true[accept]  # [M, D]: each column's gain
                        cur_true[accept] = new_true
                        pool_true.append(new_true)
                    pool.append(accepted)
                    pool_scores.append(new_scores[accept])
                    pool_steps.append(torch.full((int(accept.sum()),), step, dtype=torch.long))
                row = {
                    "step": step,
                    "accept_rate": float(accept.double().mean()),
                    "valid_rate": float(valid.double().mean()),
                    "improve_rate": float(better.double().mean()),
                    "sample_score_mean": float(new_scores[torch.isfinite(new_scores)].mean())
                    if bool(torch.isfinite(new_scores).any()) else float("nan"),
                    "score_mean": float(cur_scores.mean()),
                    "score_max": float(cur_scores.max()),
                    "length_mean": float(current.get("mask").sum(-1).double().mean()),
                }
                if domain_valid is not None:
                    row["domain_valid_rate"] = float(domain_valid.double().mean())
                row.update(extra)
                if cur_true is not None:
                    for j, (name, _, _) in enumerate(self._true_columns):
                        row.update({f"{name}_mean": float(cur_true[:, j].mean()),
                                    f"{name}_max": float(cur_true[:, j].max())})
                    if true_gain is not None:  # did the accepted samples beat what they replaced?
                        row.update(accepted_gain_stats(true_gain, [name for name, _, _ in self._true_columns]))
                stats.append(row)
                bar.set_postfix(accept=f"{row['accept_rate']:.2f}", score=f"{row['score_mean']:.3g}")
                if self.logger is not None:
                    for k, v in row.items():
                        if k != "step" and math.isfinite(v):
                            self.logger.log_scalar(f"flow/{k}", v, step=step)
                if row["accept_rate"] < self.early_stop_fraction:
                    break
        bar.close()

        # final set: top-k of {original top-k} ∪ {accepted samples}
        generated = torch.cat(pool, 0) if pool else original[:0].clone()
        generated_scores = torch.cat(pool_scores) if pool_scores else torch.zeros(0, dtype=torch.float64)
        generated_step = torch.cat(pool_steps) if pool_steps else torch.zeros(0, dtype=torch.long)
        all_trajs = torch.cat([original, generated], 0)
        all_scores = torch.cat([scores[top_idx], generated_scores])
        all_steps = torch.cat([torch.zeros(self.top_k, dtype=torch.long), generated_step])
        keep = all_scores.argsort(descending=True, stable=True)[: self.top_k]
        final = all_trajs[keep].clone()
        final_scores = all_scores[keep]
        summary: dict[str, float] = {
            "flow_steps_planned": float(steps),
            "flow_steps_run": float(len(stats)),
            "score_min_dataset": s_min,
            "score_max_dataset": s_max,
            "threshold": self.threshold,
            "candidates": float(self.candidates),
            "filter_members": float(member_scores.shape[0]),  # 1: the mean score; C: every member
            "min_length": float(min_length),
            "num_generated_accepted": float(generated.batch_size[0]),
            "fraction_generated_in_final": float((all_steps[keep] > 0).double().mean()),
            **return_summary(scores[top_idx], final_scores, prefix="score"),
        }
        if adaptive is not None:
            summary["flow_steps_adaptive"] = float(adaptive)
        true1 = None
        if true0 is not None:
            true1 = torch.cat([true0, *pool_true])[keep]
            for j, (name, _, _) in enumerate(self._true_columns):
                summary.update(return_summary(true0[:, j], true1[:, j], prefix=name))
            if self.true_return_horizon is not None:
                summary["true_return_horizon"] = float(self.true_return_horizon)
            if self.true_return_streak is not None:
                summary["true_return_streak"] = float(self.true_return_streak)
        filled = self.true_return_horizon is not None and true0 is not None
        return FlowResult(
            trajectories=final,
            scores=final_scores,
            source_step=all_steps[keep],
            original=original,
            original_scores=scores[top_idx],
            original_indices=top_idx,
            generated=generated,
            generated_step=generated_step,
            stats=stats,
            summary=summary,
            true_returns=None if true1 is None else true1[:, 0],
            original_true_returns=None if true0 is None else true0[:, 0],
            filled_true_returns=true1[:, 1] if filled else None,
            original_filled_true_returns=true0[:, 1] if filled else None,
        )

    @staticmethod
    def to_replay_buffer(
        result: FlowResult | TensorDictBase,
        *,
        buffer: ReplayBuffer | None = None,
        batch_size: int = 1024,
        seed: int = 0,
        device: torch.device | str = "cpu",
    ) -> ReplayBuffer:
        """Write the improved set's valid ``(observation, action)`` steps into a ``ReplayBuffer``.

        Trajectories are cut at their detected length (the mask). A new uniformly-sampled
        buffer is created unless ``buffer`` is given (then it is extended and returned).
        """
        trajs = result.trajectories if isinstance(result, FlowResult) else result
        flat = trajectories_to_flat(trajs.select(*TRAJ_KEYS)).select("observation", "action")
        if buffer is None:
            buffer = ReplayBuffer(
                storage=LazyTensorStorage(flat.numel(), device=device),
                sampler=RandomSampler(),
                batch_size=batch_size,
                generator=torch.Generator().manual_seed(int(seed)),
            )
        buffer.extend(flat)
        return buffer
