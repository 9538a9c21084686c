"""IQL and TD3+BC training on torchrl's losses (``IQLLoss``, ``TD3BCLoss``, ``SoftUpdate``).

The update steps follow TorchRL 0.14's ``sota-implementations/iql/iql_offline.py`` and
``td3_bc/td3_bc.py``: IQL sums actor, value and Q losses and takes one step of one
optimizer per network group, then a soft target update; TD3+BC updates the critic every
step and the actor (and the targets) every ``policy_update_delay`` steps. The loops are
hand-written, as in those recipes (torchrl's ``Trainer`` has no pure-offline path).

Example:
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> from torchrl_ftb.baselines import make_iql_model, make_offline_buffer, train_iql
    >>> trajs = make_toy_dataset(num_trajectories=8, horizon=16, seed=0)
    >>> model = make_iql_model(3, 2, hidden=(16, 16))
    >>> rb = make_offline_buffer(trajs, batch_size=32, seed=0)
    >>> stats = train_iql(model, rb, steps=5, progress=False)
    >>> sorted(k for k in stats if k.startswith("loss_"))
    ['loss_actor', 'loss_qvalue', 'loss_value']
"""
from __future__ import annotations

import math
import time
from typing import Any

import torch
import tqdm
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import ReplayBuffer
from torchrl.objectives import IQLLoss, SoftUpdate, TD3BCLoss

__all__ = ["make_iql_loss", "make_td3bc_loss", "train_iql", "train_td3bc", "log_scalars"]


def log_scalars(logger, metrics: dict[str, Any], step: int) -> None:
    """Log the finite scalar entries of ``metrics`` (never ``None``: torchrl's CSV logger crashes on it)."""
    if logger is None:
        return
    for key, value in metrics.items():
        if isinstance(value, torch.Tensor):
            if value.numel() != 1:
                continue
            value = value.item()
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            logger.log_scalar(key, float(value), step=step)


def make_iql_loss(
    model: nn.ModuleList,
    *,
    expectile: float = 0.7,
    temperature: float = 3.0,
    gamma: float = 0.99,
    loss_function: str = "l2",
    target_tau: float = 0.005,
) -> tuple[IQLLoss, SoftUpdate]:
    """torchrl ``IQLLoss`` (τ = ``expectile``, β = ``temperature``) and its ``SoftUpdate``.

    Args:
        model: ``[actor, qvalue, value]`` from :func:`~torchrl_ftb.baselines.make_iql_model`.
        expectile: expectile τ of the value regression (paper: 0.7).
        temperature: inverse temperature β of the advantage weights (paper: 3.0).
        gamma: discount.
        loss_function: Q/value regression loss (``"l2"`` as in IQL).
        target_tau: Polyak rate of the target Q-networks.
    """
    actor, qvalue, value = model
    loss = IQLLoss(
        actor, qvalue, value, loss_function=loss_function, temperature=temperature, expectile=expectile
    )
    loss.make_value_estimator(gamma=gamma)
    return loss, SoftUpdate(loss, tau=target_tau)


def make_td3bc_loss(
    model: nn.ModuleList,
    *,
    alpha: float = 2.5,
    gamma: float = 0.99,
    policy_noise: float = 0.2,
    noise_clip: float = 0.5,
    loss_function: str = "l2",
    target_tau: float = 0.005,
) -> tuple[TD3BCLoss, SoftUpdate]:
    """torchrl ``TD3BCLoss`` (BC weight α, paper: 2.5) and its ``SoftUpdate``."""
    actor, qvalue = model
    loss = TD3BCLoss(
        actor_network=actor,
        qvalue_network=qvalue,
        num_qvalue_nets=2,
        loss_function=loss_function,
        delay_actor=True,
        delay_qvalue=True,
        action_spec=actor[-1].spec,
        policy_noise=policy_noise,
        noise_clip=noise_clip,
        alpha=alpha,
    )
    loss.make_value_estimator(gamma=gamma)
    return loss, SoftUpdate(loss, tau=target_tau)


def _device_of(module: nn.Module) -> torch.device:
    return next(module.parameters()).device


def _run_loop(update, buffer: ReplayBuffer, *, steps: int, device, desc: str, progress: bool,
              logger, log_every: int, prefix: str) -> dict[str, float]:
    if steps < 1:
        raise ValueError(f"{desc}: steps must be >= 1, got {steps}")
    last: dict[str, float] = {}
    start = time.perf_counter()
    for step in tqdm.trange(steps, desc=desc, disable=not progress, mininterval=1.0):
        batch = buffer.sample().to(device)
        metrics = update(batch, step)
        if step % log_every == 0 or step == steps - 1:
            last.update({k: float(v) for k, v in metrics.items()})
            for k, v in last.items():
                if not math.isfinite(v):
                    raise FloatingPointError(f"{desc}: {k} became {v} at step {step}")
            log_scalars(logger, {f"{prefix}/{k}": v for k, v in last.items()}, step)
    last["steps"] = float(steps)
    last["train_time_s"] = time.perf_counter() - start
    return last


def train_iql(
    model: nn.ModuleList,
    buffer: ReplayBuffer,
    *,
    steps: int,
    lr: float = 3e-4,
    weight_decay: float = 0.0,
    expectile: float = 0.7,
    temperature: float = 3.0,
    gamma: float = 0.99,
    loss_function: str = "l2",
    target_tau: float = 0.005,
    seed: int | None = None,
    logger=None,
    log_every: int = 1000,
    progress: bool = True,
    device: torch.device | str | None = None,
) -> dict[str, float]:
    """Train an IQL agent on transitions sampled from ``buffer`` (rewards as its transforms give them).

    Args:
        model: ``[actor, qvalue, value]`` (moved to ``device``).
        buffer: replay buffer yielding flat transitions with ``("next", "reward")``.
        steps: gradient steps.
        lr / weight_decay: Adam settings of the three optimizers (IQL: 3e-4, 0).
        expectile, temperature, gamma, loss_function, target_tau: see :func:`make_iql_loss`.
        seed: seeds torch's global RNG (actor sampling inside the loss) before training.
        logger: torchrl logger (``log_scalar``), optional.
        log_every: logging period in steps.
        progress: show a tqdm bar.
        device: training device (default: where the model is).

    Returns:
        Last logged losses (``loss_actor``, ``loss_qvalue``, ``loss_value``), ``steps`` and
        ``train_time_s``.
    """
    if seed is not None:
        torch.manual_seed(int(seed))
    device = torch.device(device) if device is not None else _device_of(model)
    model.to(device)
    loss_module, updater = make_iql_loss(
        model, expectile=expectile, temperature=temperature, gamma=gamma,
        loss_function=loss_function, target_tau=target_tau,
    )
    optimizers = [
        torch.optim.Adam(list(params.values(True, True)), lr=lr, weight_decay=weight_decay)
        for params in (loss_module.actor_network_params, loss_module.qvalue_network_params,
                       loss_module.value_network_params)
    ]

    def update(batch: TensorDictBase, step: int) -> dict[str, torch.Tensor]:
        for opt in optimizers:
            opt.zero_grad(set_to_none=True)
        out = loss_module(batch)
        (out["loss_actor"] + out["loss_qvalue"] + out["loss_value"]).backward()
        for opt in optimizers:
            opt.step()
        updater.step()
        return {k: out[k].detach() for k in ("loss_actor", "loss_qvalue", "loss_value")}

    return _run_loop(update, buffer, steps=steps, device=device, desc="IQL", progress=progress,
                     logger=logger, log_every=log_every, prefix="iql")


def train_td3bc(
    model: nn.ModuleList,
    buffer: ReplayBuffer,
    *,
    steps: int,
    lr: float = 3e-4,
    weight_decay: float = 0.0,
    alpha: float = 2.5,
    gamma: float = 0.99,
    policy_noise: float = 0.2,
    noise_clip: float = 0.5,
    policy_update_delay: int = 2,
    loss_function: str = "l2",
    target_tau: float = 0.005,
    seed: int | None = None,
    logger=None,
    log_every: int = 1000,
    progress: bool = True,
    device: torch.device | str | None = None,
) -> dict[str, float]:
    """Train a TD3+BC agent (Fujimoto & Gu, 2021) on transitions sampled from ``buffer``.

    Args:
        model: ``[actor, qvalue]`` from :func:`~torchrl_ftb.baselines.make_td3bc_model`.
        buffer: replay buffer yielding flat transitions with ``("next", "reward")``.
        steps: critic gradient steps; the actor and targets update every ``policy_update_delay``.
        alpha: BC weight α (paper: 2.5).
        Other arguments: as :func:`train_iql`; ``policy_noise``/``noise_clip`` are TD3's
        target-policy smoothing.

    Returns:
        Last logged ``loss_qvalue``, ``loss_actor``, ``bc_loss``, ``lmbd``, ``steps``,
        ``train_time_s``.
    """
    if seed is not None:
        torch.manual_seed(int(seed))
    if policy_update_delay < 1:
        raise ValueError(f"train_td3bc: policy_update_delay must be >= 1, got {policy_update_delay}")
    device = torch.device(device) if device is not None else _device_of(model)
    model.to(device)
    loss_module, updater = make_td3bc_loss(
        model, alpha=alpha, gamma=gamma, policy_noise=policy_noise, noise_clip=noise_clip,
        loss_function=loss_function, target_tau=target_tau,
    )
    opt_actor = torch.optim.Adam(list(loss_module.actor_network_params.values(True, True)), lr=lr,
                                 weight_decay=weight_decay)
    opt_critic = torch.optim.Adam(list(loss_module.qvalue_network_params.values(True, True)), lr=lr,
                                  weight_decay=weight_decay)
    actor_metrics: dict[str, torch.Tensor] = {}

    def update(batch: TensorDictBase, step: int) -> dict[str, torch.Tensor]:
        q_loss, _ = loss_module.qvalue_loss(batch)
        opt_critic.zero_grad(set_to_none=True)
        q_loss.backward()
        opt_critic.step()
        if step % policy_update_delay == 0:
            actor_loss, meta = loss_module.actor_loss(batch)
            opt_actor.zero_grad(set_to_none=True)
            actor_loss.backward()
            opt_actor.step()
            updater.step()
            actor_metrics.update(loss_actor=actor_loss.detach(), bc_loss=meta["bc_loss"],
                                 lmbd=meta["lmbd"].detach())
        return {"loss_qvalue": q_loss.detach(), **actor_metrics}

    return _run_loop(update, buffer, steps=steps, device=device, desc="TD3+BC", progress=progress,
                     logger=logger, log_every=log_every, prefix="td3bc")
