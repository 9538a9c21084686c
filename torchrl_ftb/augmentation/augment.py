"""FTB as data augmentation for offline RL (paper §4.4, App. B.5) and the SYNTHETIC baseline.

With the rewards known, FTB needs no preference model (App. B.5): the dataset is cut into
``K`` blocks by **true return**, a conditional trajectory diffuser that also diffuses the
reward (``make_diffuser(..., reward_channel=True)``) learns block ``k`` → ``k + 1``, and the
top-``k`` trajectories by return are flowed for a fixed ``t_flow = 5`` steps. The flow keeps a
sample when its **generated return** (the masked sum of its diffused reward: the one score
definition of this stage, the same function that ranks the data, :func:`true_return`) beats
its condition's by the ratio σ on the dataset-normalised scale (:class:`FlowToBetter`).
The supplement is the generated part of the flow's final set (originals are already in the
data). SYNTHETIC (Lu et al., 2023) is the same diffuser and sampler without a condition,
trained on every trajectory: samples from the data distribution instead of better ones. Here
it generates whole trajectories with the same backbone (Lu et al. diffuse single transitions
with a residual MLP), so the two differ only in what the paper compares: *better* vs *more*.

Generated trajectories become offline-RL transitions with :func:`as_transitions`; a trajectory
that stops before the horizon ends in termination when the dataset's episodes do (locomotion
falls), otherwise its last step, which has no next observation, is dropped.

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from tensordict.nn import TensorDictModule
    >>> from torchrl_ftb.augmentation import as_transitions, flow_supplement, merge_datasets
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> data = make_toy_dataset(num_trajectories=20, horizon=8, seed=0)
    >>> def better(cond):  # a stand-in sampler: same trajectories, twice the reward
    ...     out = cond.select("observation", "action", "mask", ("next", "reward")).clone()
    ...     out["next", "reward"] = out["next", "reward"].abs() * 2 + 0.1
    ...     return out
    >>> sampler = TensorDictModule(better, ["condition"], ["sample"])
    >>> supplement, result = flow_supplement(data, sampler, top_k=5, flow_steps=2, progress=False)
    >>> supplement.batch_size[0] > 0, bool(result.scores.mean() > result.original_scores.mean())
    (True, True)
    >>> merged = merge_datasets(data, as_transitions(supplement, terminal_on_early_end=False))
    >>> merged.batch_size[0] == 20 + supplement.batch_size[0]
    True
"""
from __future__ import annotations

import hashlib
import inspect
import json
import math
from pathlib import Path
from typing import Any, Callable, Mapping

import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_ftb.data import REWARD_KEY, TERMINATED_KEY, atomic_torch_save, read_checkpoint, validate_trajectories
from torchrl_ftb.data.labels import true_return
from torchrl_ftb.data.trajectories import atomic_write_text
from torchrl_ftb.diffusion import DiffusionSampler, make_diffuser, run_settings, train_diffuser
from torchrl_ftb.flow import (
    FlowResult,
    FlowToBetter,
    clip_actions,
    default_min_length,
    masked_true_return,
    trajectory_validity,
)
from torchrl_ftb.preference import make_block_pair_buffer, make_blocks, make_trajectory_buffer

__all__ = [
    "AUGMENTATIONS",
    "TRANSITION_KEYS",
    "as_transitions",
    "build_supplement",
    "ends_in_termination",
    "flow_supplement",
    "load_supplement",
    "merge_datasets",
    "synthetic_supplement",
]

AUGMENTATIONS = {
    "none": "the dataset as it is",
    "synthetic": "SYNTHETIC: unconditional trajectory diffuser samples (Lu et al., 2023)",
    "ftb": "FTB: top-k trajectories flowed to better by a return-block conditional diffuser (§4.4)",
}
#: what an augmented dataset holds (the keys both real and generated trajectories have)
TRANSITION_KEYS: tuple = ("observation", "action", "mask", ("next", "observation"), REWARD_KEY,
                          ("next", "done"), TERMINATED_KEY, ("next", "truncated"))
GENERATED_KEYS = ("observation", "action", "mask", REWARD_KEY)
SUPPLEMENT_FORMAT = "torchrl_ftb.supplement"


def load_supplement(path: str | Path) -> tuple[TensorDict, dict[str, Any]]:
    """``(supplement [M, H], info)`` of a ``supplement.pt`` written by :func:`build_supplement`
    (``torch.load(weights_only=True)``); anything else raises a ``ValueError`` naming the file."""
    ckpt = read_checkpoint(Path(path), what="supplement")
    if not isinstance(ckpt, dict) or ckpt.get("format") != SUPPLEMENT_FORMAT:
        raise ValueError(f"{path}: not a torchrl_ftb supplement file")
    return TensorDict(ckpt["data"], batch_size=ckpt["batch_size"]), dict(ckpt["info"])


def ends_in_termination(trajs: TensorDictBase) -> bool:
    """Whether any dataset episode ends in ``("next", "terminated")`` (e.g. a locomotion fall)."""
    if TERMINATED_KEY not in trajs.keys(True):
        return False
    mask = trajs.get("mask")
    last = (mask.sum(-1) - 1).clamp(min=0)
    term = trajs.get(TERMINATED_KEY).reshape(mask.shape)
    return bool(term[torch.arange(mask.shape[0]), last].any())


def as_transitions(trajs: TensorDictBase, *, terminal_on_early_end: bool) -> TensorDict:
    """Generated trajectories ``[N, H]`` (observation, action, mask, reward) as offline-RL data.

    Adds ``("next", "observation")`` (the next step's observation), ``("next", "done" /
    "terminated" / "truncated")``. A trajectory shorter than ``H`` ends in termination if
    ``terminal_on_early_end`` (its last next-observation is never bootstrapped from; the
    observation itself stands in). Otherwise its last step has no successor and is dropped,
    and the step before it ends the episode as truncated. Trajectories left with no step
    are removed.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> gen = make_toy_dataset(num_trajectories=2, horizon=4).select("observation", "action", "mask",
        ...                                                             ("next", "reward"))
        >>> gen["mask"][1, 2:] = False
        >>> out = as_transitions(gen, terminal_on_early_end=True)
        >>> out["mask"].sum(-1).tolist(), out["next", "terminated"].squeeze(-1).sum(-1).tolist()
        ([3, 2], [0, 1])
    """
    validate_trajectories(trajs, name="as_transitions", require=[REWARD_KEY])
    obs, mask = trajs.get("observation"), trajs.get("mask").clone()
    n, horizon = mask.shape
    rows = torch.arange(n, device=mask.device)
    length = mask.sum(-1)
    terminal = (length < horizon) & bool(terminal_on_early_end)
    last = length - 1
    drop = ~terminal
    mask[rows[drop], last[drop]] = False  # no successor observation: not a transition
    length = mask.sum(-1)
    flags = torch.zeros(n, horizon, 1, dtype=torch.bool, device=mask.device)
    terminated, truncated = flags.clone(), flags.clone()
    terminated[rows[terminal], last[terminal], 0] = True
    keep_trunc = drop & (length > 0)
    truncated[rows[keep_trunc], (length - 1)[keep_trunc], 0] = True
    next_obs = torch.cat([obs[:, 1:], obs[:, -1:]], 1)
    next_obs = torch.where(terminated, obs, next_obs) * mask[..., None]  # terminal: never bootstrapped
    out = trajs.select(*GENERATED_KEYS).clone()
    out.set("mask", mask)
    m3 = mask[..., None]
    for key in ("observation", "action", REWARD_KEY):
        out.set(key, out.get(key) * m3)
    out.set(("next", "observation"), next_obs)
    out.set(TERMINATED_KEY, terminated)
    out.set(("next", "truncated"), truncated)
    out.set(("next", "done"), terminated | truncated)
    return out[length > 0]


def merge_datasets(original: TensorDictBase, supplement: TensorDictBase) -> TensorDict:
    """``original`` ∪ ``supplement`` on :data:`TRANSITION_KEYS` (same horizon), originals first."""
    for td, name in ((original, "original"), (supplement, "supplement")):
        validate_trajectories(td, name=f"merge_datasets: {name}", require=TRANSITION_KEYS[3:])
    if original.batch_size[1] != supplement.batch_size[1]:
        raise ValueError(f"merge_datasets: horizons differ ({original.batch_size[1]} vs {supplement.batch_size[1]})")
    a = original.select(*TRANSITION_KEYS)
    b = supplement.select(*TRANSITION_KEYS).to(a.device)
    for key in TRANSITION_KEYS:  # e.g. float rewards vs float64, bool flags stored as [N, H]
        b.set(key, b.get(key).to(a.get(key).dtype).reshape(b.batch_size + a.get(key).shape[2:]))
    return torch.cat([a, b], 0)


def flow_supplement(
    data: TensorDictBase,
    sampler: Callable[[TensorDictBase], TensorDictBase],
    *,
    top_k: int = 100,
    flow_steps: int = 5,
    threshold: float = 1.05,
    early_stop_fraction: float = 0.0,
    max_abs_z: float = 30.0,
    action_tolerance: float = 0.5,
    min_length: int | None = None,
    true_reward_fn: Callable | None = None,
    batch_size: int = 256,
    seed: int = 0,
    logger: Any = None,
    progress: bool = True,
) -> tuple[TensorDict, FlowResult]:
    """FTB's supplement (App. B.5): flow the top-``k`` by return, keep the generated final trajectories.

    Args:
        data: ``[N, H]`` dataset with ``("next", "reward")``.
        sampler: ``"condition" -> "sample"`` module whose samples carry ``("next", "reward")``
            (a :class:`~torchrl_ftb.diffusion.DiffusionSampler` of a ``reward_channel`` diffuser).

    Keyword Args:
        top_k, flow_steps, threshold: the flow (App. B.5: 100 trajectories, ``t_flow = 5``; σ as
            D4RL's FTB, 1.05); ``early_stop_fraction``: 0 runs every step (the paper's fixed
            ``t_flow``). Validity and the rest: :class:`~torchrl_ftb.flow.FlowToBetter`.
        true_reward_fn: ground-truth reward, for statistics only.

    Returns:
        ``(supplement [M, H], flow result)``: the final set's generated trajectories
        (observation, action, mask, generated reward), ``M <= top_k``.
    """
    flow = FlowToBetter(
        sampler, true_return, top_k=top_k, threshold=threshold, flow_steps=flow_steps,
        early_stop_fraction=early_stop_fraction, max_abs_z=max_abs_z, action_tolerance=action_tolerance,
        min_length=min_length, true_reward_fn=true_reward_fn, batch_size=batch_size, seed=seed,
        keep_reward=True, logger=logger, progress=progress,
    )
    result = flow(data, scores=true_return(data))
    return result.trajectories[result.source_step > 0].clone(), result


@torch.no_grad()
def synthetic_supplement(
    sampler: Callable[[TensorDictBase], TensorDictBase],
    *,
    num_samples: int,
    normalizer: Any | None,
    min_length: int = 2,
    max_abs_z: float = 30.0,
    action_limit: float = 1.0,
    action_tolerance: float = 0.5,
    batch_size: int = 256,
) -> tuple[TensorDict, dict[str, float]]:
    """SYNTHETIC's supplement: ``num_samples`` unconditional samples, the valid ones kept.

    ``sampler`` is a :class:`~torchrl_ftb.diffusion.DiffusionSampler` of an unconditional
    ``reward_channel`` diffuser; validity is the flow's (:func:`trajectory_validity`), actions
    clipped to ``action_limit`` afterwards as the flow does.

    Returns:
        ``(valid samples [M, H], {"generated", "valid", "valid_rate"})``.
    """
    if num_samples < 1:
        raise ValueError(f"synthetic_supplement: num_samples must be >= 1, got {num_samples}")
    chunks = []
    for start in range(0, num_samples, batch_size):
        n = min(batch_size, num_samples - start)
        out = sampler(TensorDict({}, batch_size=[n])).get("sample")
        if REWARD_KEY not in out.keys(True):
            raise ValueError("synthetic_supplement: the sampler's samples have no ('next', 'reward'); "
                             "use a diffuser with reward_channel=True")
        chunks.append(out.select(*GENERATED_KEYS).cpu())
    samples = torch.cat(chunks, 0)
    samples.set("mask", samples.get("mask").bool())
    valid = trajectory_validity(samples, normalizer=normalizer, max_abs_z=max_abs_z, min_length=min_length,
                                action_limit=action_limit, action_tolerance=action_tolerance)["valid"]
    kept = clip_actions(samples[valid].clone(), action_limit)
    return kept, {"generated": float(num_samples), "valid": float(valid.sum()),
                  "valid_rate": float(valid.double().mean())}


def _check_options(options: Mapping[str, Any], fn: Callable, section: str, *, reserved: tuple = ()) -> None:
    """Raise a clear error for option names ``fn`` does not take (or that the stage sets itself)."""
    allowed = [k for k, p in inspect.signature(fn).parameters.items()
               if p.kind is inspect.Parameter.KEYWORD_ONLY and k not in reserved]
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ValueError(f"build_supplement: unknown {section} option(s) {unknown}; valid: {sorted(allowed)}")


def _fingerprint(trajs: TensorDictBase) -> str:
    """A content hash of a dataset's valid (observation, action, reward) steps and termination flags (which
    decide how a generated trajectory that ends early is closed, :func:`ends_in_termination`)."""
    mask = trajs.get("mask")
    h = hashlib.sha256(str(list(trajs.batch_size)).encode())
    keys = ["observation", "action", REWARD_KEY] + ([TERMINATED_KEY] if TERMINATED_KEY in trajs.keys(True) else [])
    for key in keys:
        h.update(trajs.get(key)[mask].detach().to(torch.float32).cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def build_supplement(
    kind: str,
    trajs: TensorDictBase,
    *,
    cache_dir: str | Path,
    diffuser: Mapping[str, Any],
    flow: Mapping[str, Any],
    synthetic: Mapping[str, Any] | None = None,
    num_blocks: int = 10,
    seed: int = 0,
    true_reward_fn: Callable | None = None,
    oracle_step: Callable | None = None,
    readings: Mapping[str, Callable[[TensorDictBase], torch.Tensor]] | None = None,
    device: torch.device | str = "cpu",
    resume: bool = True,
    logger: Any = None,
    progress: bool = True,
) -> tuple[TensorDict, dict[str, Any]]:
    """Train the stage's diffuser and generate the supplement, cached and resumable.

    Everything lives in ``cache_dir/<kind>-<hash>/`` (the hash covers the dataset's content and
    every setting below): ``config.json``, the diffuser's checkpoints (a killed run resumes
    from the last one) and ``supplement.pt`` (``torch.load(weights_only=True)``). A finished
    supplement is loaded instead of rebuilt, so several offline-RL methods share one.

    Args:
        kind: ``"ftb"`` or ``"synthetic"`` (:data:`AUGMENTATIONS`; ``"none"`` needs no supplement).
        trajs: the ``[N, H]`` dataset with ``("next", "reward")``.

    Keyword Args:
        cache_dir: where the stage's directory goes.
        diffuser: ``preset`` (``cpu`` | ``paper`` | ``tiny``), ``overrides`` (model fields) and the
            :func:`~torchrl_ftb.diffusion.run_settings` numbers (``steps``, ``batch_size``, ``lr``,
            ``grad_clip``, ``sampler``, ``sample_steps``, ``guidance``; ``None``: the preset's),
            ``checkpoint_every``, ``autocast_bf16``.
        flow: :func:`flow_supplement` options (``top_k``, ``flow_steps``, ``threshold``, ...).
        synthetic: :func:`synthetic_supplement` options, ``num_samples`` (default: ``flow["top_k"]``,
            as many trajectories as FTB's supplement can hold at most), ``batch_size``,
            ``action_limit``; validity as the flow's (``flow["max_abs_z"]``, ``["action_tolerance"]``).
        num_blocks: return blocks ``K`` of the conditional diffuser (``"ftb"``).
        seed: seeds the diffuser's training and the sampler noise.
        true_reward_fn: ground-truth reward; the supplement's true return and the generated
            reward's error are reported with it.
        oracle_step: ground-truth dynamics ``(observation, action) -> next observation`` (e.g.
            ``partial(torchrl_ftb.envs.oracle_step, "hopper")``); the supplement's per-step
            dynamics error (:func:`~torchrl_ftb.analysis.dynamics_error`) is reported with it.
        readings: ``{name: trajectories [M, H] -> returns [M]}``, the supplement executed in the simulator, e.g.
            ``{"replayed": lambda t: torchrl_ftb.analysis.locomotion_replays("hopper", t)[0]}`` (open loop) or
            ``{"tracked": lambda t: torchrl_ftb.analysis.locomotion_tracked_returns("hopper", t)[0]}`` (closed
            loop); each one's ``{name}_return_mean`` / ``_max`` is reported, for a cached supplement too (not
            stored).

    Returns:
        ``(supplement [M, H] with TRANSITION_KEYS, info)``; ``info`` has the counts, the
        generated vs the dataset's returns, the diffuser's training summary and ``path``.
    """
    if kind not in ("ftb", "synthetic"):
        raise ValueError(f"build_supplement: kind must be 'ftb' or 'synthetic' (see AUGMENTATIONS), got {kind!r}")
    validate_trajectories(trajs, name="build_supplement: dataset", require=[REWARD_KEY])
    d = dict(diffuser)
    preset, overrides = str(d.pop("preset", "cpu")), dict(d.pop("overrides", None) or {})
    checkpoint_every, bf16 = int(d.pop("checkpoint_every", 500)), bool(d.pop("autocast_bf16", False))
    _check_options(d, run_settings, "diffuser")
    settings = run_settings(preset, **d)
    flow_opts = dict(flow)
    _check_options(flow_opts, flow_supplement, "flow", reserved=("true_reward_fn", "seed", "logger", "progress"))
    _check_options(dict(synthetic or {}), synthetic_supplement, "synthetic", reserved=(
        "normalizer", "min_length", "max_abs_z", "action_tolerance"))
    syn = {"num_samples": int(flow_opts.get("top_k", 100)), **dict(synthetic or {})}
    config = {"kind": kind, "dataset": _fingerprint(trajs), "preset": preset, "overrides": overrides,
              "settings": settings, "seed": int(seed)}
    if kind == "ftb":
        config.update(flow=flow_opts, num_blocks=int(num_blocks))
    else:  # SYNTHETIC's validity rules are the flow's: they belong to its cache key too (a changed limit re-filters)
        validity = {"max_abs_z": float(flow_opts.get("max_abs_z", 30.0)),
                    "action_tolerance": float(flow_opts.get("action_tolerance", 0.5)),
                    "min_length": int(flow_opts.get("min_length") or default_min_length(trajs))}
        config.update(synthetic=syn, validity=validity)
    digest = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:12]
    path = Path(cache_dir).expanduser() / f"{kind}-{digest}"
    path.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path / "config.json", json.dumps(config, indent=2, default=str))
    out_file = path / "supplement.pt"
    if resume and out_file.exists():
        supplement, info = load_supplement(out_file)
        return supplement, {**info, **_readings(supplement, readings), "path": str(path), "loaded": True}

    obs_dim, act_dim = trajs.get("observation").shape[-1], trajs.get("action").shape[-1]
    horizon = int(trajs.batch_size[1])
    model = make_diffuser(preset, obs_dim=obs_dim, action_dim=act_dim, horizon=horizon, reward_channel=True,
                          unconditional=kind == "synthetic", data=trajs, **overrides).to(device)
    returns = true_return(trajs).cpu()
    if kind == "ftb":
        block_ids = make_blocks(returns, int(num_blocks), seed=int(seed))
        buffer = make_block_pair_buffer(trajs, block_ids, batch_size=settings["batch_size"], seed=seed,
                                       keys=GENERATED_KEYS, scores=returns if model.score_condition else None)
    else:
        buffer = make_trajectory_buffer(trajs, batch_size=settings["batch_size"], seed=seed,
                                       keys=GENERATED_KEYS)
    train = train_diffuser(model, buffer, steps=settings["steps"], lr=settings["lr"],
                           grad_clip=settings["grad_clip"], logger=logger, checkpoint_dir=path / "diffuser",
                           checkpoint_every=checkpoint_every, resume=resume, progress=progress, device=device,
                           autocast_bf16=bf16, seed=int(seed))
    generator = torch.Generator(device=model.normalizer.mean.device).manual_seed(int(seed))
    sampler = DiffusionSampler(model, sampler=settings["sampler"], steps=settings["sample_steps"],
                               guidance=settings["guidance"], generator=generator, autocast_bf16=bf16)
    info: dict[str, Any] = {"kind": kind, "diffuser": {k: train[k] for k in ("step", "final_loss", "wall_time_s",
                                                                             "resumed_from")}}
    if kind == "ftb":
        generated, result = flow_supplement(trajs, sampler, true_reward_fn=true_reward_fn, seed=int(seed),
                                            logger=logger, progress=progress, **flow_opts)
        info["flow"] = result.summary
        info["flow_stats"] = result.stats
        info["block_sizes"] = torch.bincount(block_ids).tolist()
    else:
        # the flow's validity rules; the shortest length: flow.min_length where set, else half the dataset's
        # shortest (an unconditional model samples the whole dataset, the flow only its top-k)
        generated, info["synthetic"] = synthetic_supplement(sampler, normalizer=model.normalizer, **validity, **syn)
    info.update(_describe(generated, returns, true_reward_fn))
    supplement = as_transitions(generated, terminal_on_early_end=ends_in_termination(trajs)) if generated.batch_size[0] \
        else generated
    if oracle_step is not None and supplement.batch_size[0]:
        from torchrl_ftb.analysis import dynamics_error  # here: the package pulls in matplotlib

        info["dynamics_error_mean"] = dynamics_error(supplement, oracle_step)["mean"]
    info["num_trajectories"] = int(supplement.batch_size[0])
    info["num_transitions"] = int(supplement.get("mask").sum()) if supplement.batch_size[0] else 0
    info["dataset_transitions"] = int(trajs.get("mask").sum())
    atomic_torch_save({"format": SUPPLEMENT_FORMAT, "data": supplement.to_dict(),
                       "batch_size": list(supplement.batch_size), "info": info}, out_file)
    return supplement, {**info, **_readings(supplement, readings), "path": str(path), "loaded": False}


def _readings(supplement: TensorDictBase, readings: Mapping[str, Callable] | None) -> dict[str, float]:
    """The supplement's returns as each of ``readings`` executes it, beside the true reward of its own transitions."""
    out: dict[str, float] = {}
    if not supplement.batch_size[0]:
        return out
    for name, fn in (readings or {}).items():
        returns = torch.as_tensor(fn(supplement), dtype=torch.float64)
        out.update({f"{name}_return_mean": float(returns.mean()), f"{name}_return_max": float(returns.max())})
    return out


def _describe(generated: TensorDictBase, data_returns: torch.Tensor, true_reward_fn: Callable | None) -> dict:
    """Generated vs dataset returns (and, with the oracle, the generated reward's error)."""
    out: dict[str, Any] = {"dataset_return_mean": float(data_returns.mean()),
                           "dataset_return_max": float(data_returns.max())}
    if not generated.batch_size[0]:
        return out
    gen_ret = true_return(generated).cpu()
    out.update(generated_return_mean=float(gen_ret.mean()), generated_return_max=float(gen_ret.max()),
               generated_length_mean=float(generated.get("mask").sum(-1).double().mean()))
    if true_reward_fn is not None:
        true_ret = masked_true_return(generated, true_reward_fn)
        out.update(true_return_mean=float(true_ret.mean()), true_return_max=float(true_ret.max()),
                   generated_minus_true_return_mean=float((gen_ret.double() - true_ret).mean()))
    return {k: (v if not isinstance(v, float) or math.isfinite(v) else None) for k, v in out.items()}
