"""Training loop, checkpoints and save/load of the trajectory diffuser.

Checkpoints are plain dicts (config, state_dict incl. EMA and normaliser buffers,
optimiser, step, torch RNG states) written atomically and read with
``torch.load(weights_only=True)``. ``resume=True`` restores all of it, so a resumed run
continues the same random stream (replay-buffer samplers drawing from torch's global RNG
included).

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_ftb.diffusion import make_diffuser, train_diffuser
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> data = make_toy_dataset(num_trajectories=8, horizon=8, seed=0)
    >>> diffuser = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=8).fit_normalizer(data)
    >>> batches = lambda: TensorDict({"condition": data[:4], "target": data[4:]}, batch_size=[4])
    >>> out = train_diffuser(diffuser, batches, steps=2, progress=False)
    >>> out["step"]
    2
"""
from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Any, Callable

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_ftb.data.trajectories import atomic_torch_save, read_checkpoint, restore_sampler_rng, sampler_rng_state
from torchrl_ftb.diffusion.loss import DiffusionLoss
from torchrl_ftb.diffusion.model import TrajectoryDiffuser

__all__ = ["train_diffuser", "save_diffuser", "load_diffuser", "CHECKPOINT_NAME"]

CHECKPOINT_FORMAT = "torchrl_ftb.diffuser"
CHECKPOINT_VERSION = 1
CHECKPOINT_NAME = "diffuser_last.pt"


def _read_checkpoint(path: str | os.PathLike, map_location: Any = "cpu") -> dict:
    ckpt = read_checkpoint(path, what="diffuser", map_location=map_location)
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a torchrl_ftb diffuser checkpoint (missing format tag)")
    if ckpt.get("format_version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint format_version {ckpt.get('format_version')!r} "
                         f"is not supported (expected {CHECKPOINT_VERSION})")
    return ckpt


def _load_state(diffuser: TrajectoryDiffuser, ckpt: dict, path: str | os.PathLike) -> None:
    try:
        diffuser.load_state_dict(ckpt["state_dict"], strict=True)
    except (RuntimeError, KeyError) as err:
        raise ValueError(f"{path}: checkpoint does not match this diffuser (config in file: "
                         f"{ckpt.get('config')}, diffuser config: {diffuser.config}): {err}") from err


def save_diffuser(diffuser: TrajectoryDiffuser, path: str | os.PathLike, *, extra: dict | None = None) -> Path:
    """Atomically save config + weights (raw, EMA, normaliser) to ``path``.

    Args:
        diffuser: the model.
        path: target file.
        extra: more weights_only-loadable entries (the trainer adds optimizer, step, RNG).
    """
    payload = {
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        "config": diffuser.config,
        "state_dict": diffuser.state_dict(),
        **(extra or {}),
    }
    atomic_torch_save(payload, path)
    return Path(path)


def load_diffuser(
    path: str | os.PathLike,
    *,
    diffuser: TrajectoryDiffuser | None = None,
    map_location: Any = "cpu",
) -> TrajectoryDiffuser:
    """Load a diffuser saved by :func:`save_diffuser` or :func:`train_diffuser`.

    Args:
        path: checkpoint file.
        diffuser: load into this model; if ``None`` it is rebuilt from the stored
            ``config`` with :func:`~torchrl_ftb.diffusion.make_diffuser`.
        map_location: device for the loaded tensors.

    Raises:
        FileNotFoundError: no file.
        ValueError: corrupt file, wrong format, or weights that do not fit the model.
    """
    ckpt = _read_checkpoint(path, map_location)
    if diffuser is None:
        cfg = ckpt.get("config")
        if not cfg:
            raise ValueError(f"{path}: checkpoint has no config; pass diffuser= to load into")
        from torchrl_ftb.diffusion.presets import make_diffuser

        cfg = dict(cfg)
        cfg.setdefault("global_condition", False)  # checkpoints from before the options had none
        cfg.setdefault("concat_condition", False)
        cfg.setdefault("score_condition", False)
        diffuser = make_diffuser(cfg.pop("preset"), **cfg)
    _load_state(diffuser, ckpt, path)
    return diffuser.to(map_location) if map_location is not None else diffuser


def train_diffuser(
    diffuser: TrajectoryDiffuser,
    replay_buffer: Any,
    *,
    steps: int,
    lr: float = 1e-4,
    ema_decay: float | None = None,
    grad_clip: float | None = None,
    weight_decay: float = 0.0,
    logger: Any = None,
    log_every: int = 50,
    checkpoint_dir: str | os.PathLike | None = None,
    checkpoint_every: int = 1000,
    resume: bool = False,
    progress: bool = True,
    device: torch.device | str | None = None,
    compile: bool = False,
    autocast_bf16: bool = False,
    seed: int = 0,
    loss_module: DiffusionLoss | None = None,
) -> dict:
    """Train the diffuser on pair batches; EMA updated every step; periodic atomic checkpoints.

    Args:
        diffuser: model with a fitted normaliser.
        replay_buffer: anything with ``.sample()`` (a torchrl ``ReplayBuffer`` with the block
            pair sampler) or a callable, returning a pair batch ``[B]`` with
            ``"condition"``/``"target"`` ``[B, H]``.
        steps: total optimisation steps (a resumed run continues up to this number).
        lr: Adam learning rate (paper: 1e-4).
        ema_decay: EMA decay (default: the diffuser's).
        grad_clip: max global grad norm (``None``: no clipping, as the authors).
        weight_decay: Adam weight decay.
        logger: a ``torchrl.record.loggers.Logger`` (``log_scalar``), or ``None``.
        log_every: logging period in steps.
        checkpoint_dir: where ``diffuser_last.pt`` is written (``None``: no checkpoints).
        checkpoint_every: checkpoint period in steps (a final one is always written).
        resume: continue from ``checkpoint_dir/diffuser_last.pt`` if it exists (weights, optimiser, torch's RNG
            and the replay buffer's own generator: the run goes on as an uninterrupted one would).
        progress: tqdm progress bar.
        device: training device (default: where the diffuser is).
        compile: ``torch.compile`` the backbone.
        autocast_bf16: bf16 autocast for forward/loss.
        seed: torch seed at the start of a fresh run.
        loss_module: a configured :class:`DiffusionLoss` (e.g. with ``set_keys``); default one.

    Returns:
        ``{"step", "final_loss", "losses" (this run, per step), "wall_time_s",
        "trajectories_per_s", "resumed_from", "checkpoint"}``.
    """
    if steps < 0:
        raise ValueError(f"train_diffuser: steps must be >= 0, got {steps}")
    diffuser._check_fitted()
    device = torch.device(device) if device is not None else diffuser.normalizer.mean.device
    diffuser.to(device)
    loss_module = loss_module if loss_module is not None else DiffusionLoss(diffuser)
    if loss_module.diffuser is not diffuser:
        raise ValueError("train_diffuser: loss_module wraps a different diffuser")
    sample: Callable[[], TensorDictBase] = replay_buffer.sample if hasattr(replay_buffer, "sample") else replay_buffer
    if ema_decay is not None:
        diffuser.set_ema_decay(ema_decay)
    optimizer = torch.optim.Adam(diffuser.trainable_parameters(), lr=lr, weight_decay=weight_decay)
    ckpt_path = Path(checkpoint_dir) / CHECKPOINT_NAME if checkpoint_dir is not None else None

    start = 0
    if resume and ckpt_path is not None and ckpt_path.exists():
        ckpt = _read_checkpoint(ckpt_path, map_location=device)
        _load_state(diffuser, ckpt, ckpt_path)
        optimizer.load_state_dict(ckpt["optimizer"])
        start = int(ckpt["step"])
        torch.set_rng_state(ckpt["rng_torch"].cpu())
        restore_sampler_rng(replay_buffer, ckpt.get("rng_sampler"))  # checkpoints before session 36 lack it
        if torch.cuda.is_available() and ckpt.get("rng_cuda"):
            torch.cuda.set_rng_state_all([s.cpu() for s in ckpt["rng_cuda"]])
    else:
        torch.manual_seed(seed)
    if compile:
        diffuser.backbone.compile()

    def checkpoint(step: int) -> None:
        if ckpt_path is None:
            return
        extra = {
            "optimizer": optimizer.state_dict(),
            "step": step,
            "rng_torch": torch.get_rng_state(),
            "rng_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        }
        if (rng := sampler_rng_state(replay_buffer)) is not None:  # the pair buffer's own generator
            extra["rng_sampler"] = rng
        save_diffuser(diffuser, ckpt_path, extra=extra)

    losses: list[float] = []
    n_traj = 0
    t0 = time.perf_counter()
    diffuser.networks.train()
    bar = tqdm(range(start, steps), desc="diffuser", disable=not progress, initial=start, total=steps)
    for step in bar:
        batch = sample().to(device)
        with torch.autocast(device.type, dtype=torch.bfloat16) if autocast_bf16 else contextlib.nullcontext():
            out = loss_module(batch)
        loss = out["loss_diffusion"]
        if not torch.isfinite(loss):
            raise FloatingPointError(f"train_diffuser: non-finite loss at step {step}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = (torch.nn.utils.clip_grad_norm_(diffuser.trainable_parameters(), grad_clip)
                     if grad_clip is not None else None)
        optimizer.step()
        diffuser.update_ema()
        value = float(loss.detach())
        losses.append(value)
        n_traj += batch.batch_size[0]
        if progress:
            bar.set_postfix(loss=f"{value:.4f}")
        done = step + 1
        if logger is not None and (done % log_every == 0 or done == steps):
            logger.log_scalar("diffuser/loss_diffusion", value, step=done)
            logger.log_scalar("diffuser/mse_data", float(out["diffusion_mse_data"]), step=done)
            logger.log_scalar("diffuser/mse_validity", float(out["diffusion_mse_validity"]), step=done)
            if grad_norm is not None:
                logger.log_scalar("diffuser/grad_norm", float(grad_norm), step=done)
        if checkpoint_every and done % checkpoint_every == 0 and done != steps:
            checkpoint(done)
    bar.close()
    final_step = max(start, steps)
    if ckpt_path is not None and (losses or not ckpt_path.exists()):
        checkpoint(final_step)
    wall = time.perf_counter() - t0
    return {
        "step": final_step,
        "final_loss": losses[-1] if losses else None,
        "losses": losses,
        "wall_time_s": wall,
        "trajectories_per_s": n_traj / wall if wall > 0 and n_traj else 0.0,
        "resumed_from": start,
        "checkpoint": str(ckpt_path) if ckpt_path is not None else None,
    }
