"""Analysis of generated trajectories (paper §4.3): improvement, validity, novelty.

* :func:`improvement` — true return of the original top-k vs the flowed set (mean / max).
* :func:`dynamics_error` — validity: per-step error of generated transitions against an
  oracle ``(s_h, a_h) -> s_{h+1}`` (the env helpers: ``torchrl_ftb.envs.oracle_step`` for
  locomotion; :func:`toy_oracle_step` for the toy task).
* :func:`fit_dynamics_reference` — the paper's reference scale for that error (Fig. 4 right, dashed line):
  an MLP one-step model fitted on part of the dataset, scored the same way on the rest.
* :func:`novelty` — min L2 distance of each generated trajectory to the dataset, beside the
  same distance for Gaussian-perturbed dataset trajectories (N(0, 0.1), the paper's baseline).

Example:
    >>> import torch
    >>> from torchrl_ftb.testing import make_toy_dataset, toy_reward
    >>> data = make_toy_dataset(num_trajectories=8, horizon=8, seed=0)
    >>> out = improvement(data[:4], data[4:], true_reward_fn=toy_reward)
    >>> sorted(out)
    ['true_return_max_after', 'true_return_max_before', 'true_return_mean_after', 'true_return_mean_before']
    >>> oracle = lambda o, a: toy_oracle_step(o, a, horizon=8)
    >>> float(dynamics_error(data, oracle)["mean"]) < 1e-5  # real data obey the dynamics
    True
"""
from __future__ import annotations

from typing import Callable

import torch
from tensordict import TensorDictBase

from torchrl_ftb.flow.flow import masked_true_return, return_summary

__all__ = ["improvement", "dynamics_error", "fit_dynamics_reference", "per_step_mean", "toy_oracle_step", "novelty",
           "trajectory_distances"]


def improvement(
    original: TensorDictBase,
    flowed: TensorDictBase,
    *,
    true_reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    horizon: int | None = None,
) -> dict[str, float]:
    """Mean and max true return of the original top-k and of the flowed set (same reward fn).

    Args:
        original: the starting top-k ``[k, H]``.
        flowed: the flowed set ``[k', H]``.
        true_reward_fn: ``(observation, action) -> reward`` ground truth.
        horizon: the stop-rule fill of :func:`~torchrl_ftb.flow.flow.masked_true_returns`
            (``None``: the plain sum).

    Returns:
        ``{"true_return_mean_before", "true_return_max_before", "true_return_mean_after",
        "true_return_max_after"}``.
    """
    return return_summary(masked_true_return(original, true_reward_fn, horizon=horizon),
                          masked_true_return(flowed, true_reward_fn, horizon=horizon))


def toy_oracle_step(observation: torch.Tensor, action: torch.Tensor, *, horizon: int) -> torch.Tensor:
    """Exact next observation of :class:`~torchrl_ftb.testing.ToyLineEnv` data (``p' = p + dt a``).

    The time feature (``obs[2] = h / H``) advances by ``1 / horizon``.
    """
    from torchrl_ftb.testing.mocks import TOY_DT

    nxt = observation.clone()
    nxt[..., :2] = observation[..., :2] + TOY_DT * action.clamp(-1.0, 1.0)
    nxt[..., 2] = observation[..., 2] + 1.0 / horizon
    return nxt


def _successors(trajectories: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """``(s_{h+1} [N, H, obs], valid [N, H])``: ``("next", "observation")`` where the batch has it (every valid
    step is a transition), else the next observation of the trajectory itself, the last valid step excluded."""
    obs, mask = trajectories.get("observation"), trajectories.get("mask").bool()
    if ("next", "observation") in trajectories.keys(True):
        return trajectories.get(("next", "observation")), mask
    return (torch.cat([obs[:, 1:], obs[:, -1:]], 1),
            mask & torch.cat([mask[:, 1:], torch.zeros_like(mask[:, :1])], 1))


def dynamics_error(
    trajectories: TensorDictBase,
    oracle_step: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
) -> dict[str, torch.Tensor | float]:
    """Per-step ``||s_{h+1} - oracle(s_h, a_h)||_1 / obs_dim`` on steps with a successor.

    ``s_{h+1}`` is ``("next", "observation")`` where the batch has it (every valid step is a
    transition), else the next *generated* observation (``observation`` shifted by one), so
    the last valid step of each trajectory has no target and is excluded.

    Args:
        trajectories: ``[N, H]`` batch (``observation``, ``action``, ``mask``).
        oracle_step: ``(observation [M, obs], action [M, act]) -> next observation [M, obs]``,
            e.g. ``functools.partial(torchrl_ftb.envs.oracle_step, "hopper")``.

    Returns:
        ``{"per_step": [N, H] (0 where no target), "valid": [N, H] bool, "per_trajectory": [N],
        "mean": float}``.
    """
    obs, act = trajectories.get("observation"), trajectories.get("action")
    target, valid = _successors(trajectories)
    err = torch.zeros(valid.shape, dtype=torch.float32, device=obs.device)
    if bool(valid.any()):
        pred = torch.as_tensor(oracle_step(obs[valid], act[valid])).to(obs.device).float()
        err[valid] = (pred - target[valid].float()).abs().mean(-1)
    counts = valid.sum(-1).clamp_min(1)
    per_traj = err.sum(-1) / counts
    return {"per_step": err, "valid": valid, "per_trajectory": per_traj,
            "mean": float(err[valid].mean()) if bool(valid.any()) else float("nan")}


def per_step_mean(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``[H]`` mean of ``values [N, H]`` over the trajectories valid at each step (NaN where none is), e.g. the
    generated transitions' error by step within the trajectory (paper Fig. 4 right) from :func:`dynamics_error`.

    Example:
        >>> per_step_mean(torch.tensor([[1.0, 2.0], [3.0, 0.0]]), torch.tensor([[True, True], [True, False]]))
        tensor([2., 2.])
    """
    valid = valid.bool()
    counts = valid.sum(0)
    total = torch.where(valid, values, torch.zeros_like(values)).sum(0)
    return torch.where(counts > 0, total / counts.clamp_min(1), torch.full_like(total, float("nan")))


def _transitions(trajectories: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(s, a, s')`` of every step with a successor (:func:`_successors`), flat, on the CPU."""
    target, valid = _successors(trajectories)
    obs, act = trajectories.get("observation"), trajectories.get("action")
    return obs[valid].float().cpu(), act[valid].float().cpu(), target[valid].float().cpu()


def fit_dynamics_reference(data: TensorDictBase, *, steps: int = 2000, batch_size: int = 256, hidden: int = 256,
                           lr: float = 1e-3, holdout: float = 0.2, seed: int = 0) -> dict[str, float]:
    """The paper's reference scale for :func:`dynamics_error` (§4.3, Fig. 4 right, dashed line): a learned
    one-step model's error on real transitions it was not fitted on.

    An MLP (torchrl's ``MLP``, two hidden layers of ``hidden`` ReLU units) maps the normalised ``(s, a)`` to the
    normalised change ``s' - s``; it is fitted on the transitions of a ``1 - holdout`` share of the trajectories and
    scored, as :func:`dynamics_error` scores an oracle's prediction (mean absolute error per observation dimension),
    on the transitions of the others. A hand-written regression loop: a supervised fit used only by this analysis,
    which no torchrl loss covers. Seeded: the same data and seed give the same number.

    Args:
        data: ``[N, H]`` real trajectories (``observation``, ``action``, ``mask``; ``("next", "observation")`` if
            present), at least two.
        steps, batch_size, hidden, lr: Adam steps on the mean squared error, its batch, the width, the step size.
        holdout: share of the trajectories held out (at least one).
        seed: the split, the initialisation and the batches.

    Returns:
        ``{"heldout_error": float, "train_error": float, "train_transitions": int, "heldout_transitions": int}``.

    Raises:
        ValueError: fewer than two trajectories, no transition on either side, or ``steps < 1``.

    Example:
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> ref = fit_dynamics_reference(make_toy_dataset(num_trajectories=8, horizon=8, seed=0), steps=20)
        >>> ref["heldout_transitions"] > 0 and ref["heldout_error"] > 0
        True
    """
    from torchrl.modules import MLP  # here: the package's import stays light

    n = data.batch_size[0]
    if n < 2 or steps < 1 or not 0.0 < holdout < 1.0:
        raise ValueError(f"fit_dynamics_reference: need >= 2 trajectories, steps >= 1 and holdout in (0, 1), got "
                         f"{n}, {steps}, {holdout}")
    gen = torch.Generator().manual_seed(seed)
    order = torch.randperm(n, generator=gen)
    n_out = min(n - 1, max(1, round(holdout * n)))
    (s, a, s1), (s_out, a_out, s1_out) = (_transitions(data[order[n_out:]]), _transitions(data[order[:n_out]]))
    if not len(s) or not len(s_out):
        raise ValueError("fit_dynamics_reference: the data have no transition (two consecutive valid steps) on one "
                         "side of the split")
    x = torch.cat([s, a], -1)
    x_loc, x_scale = x.mean(0), x.std(0).clamp_min(1e-6)
    d_loc, d_scale = (s1 - s).mean(0), (s1 - s).std(0).clamp_min(1e-6)
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        net = MLP(in_features=x.shape[-1], out_features=s.shape[-1], num_cells=[hidden, hidden], activation_class=torch.nn.ReLU)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    xn, yn = (x - x_loc) / x_scale, ((s1 - s) - d_loc) / d_scale
    for _ in range(steps):
        idx = torch.randint(0, len(xn), (min(batch_size, len(xn)),), generator=gen)
        loss = (net(xn[idx]) - yn[idx]).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    def error(s_, a_, s1_) -> float:
        with torch.no_grad():
            pred = s_ + net((torch.cat([s_, a_], -1) - x_loc) / x_scale) * d_scale + d_loc
        return float((pred - s1_).abs().mean())

    return {"heldout_error": error(s_out, a_out, s1_out), "train_error": error(s, a, s1),
            "train_transitions": len(s), "heldout_transitions": len(s_out)}


def _flat_features(trajs: TensorDictBase) -> torch.Tensor:
    mask = trajs.get("mask").bool()[..., None]
    x = torch.cat([trajs.get("observation"), trajs.get("action")], -1).float() * mask
    return x.reshape(x.shape[0], -1)


def trajectory_distances(a: TensorDictBase, b: TensorDictBase, *, chunk: int = 256) -> torch.Tensor:
    """Min L2 distance of each trajectory of ``a`` to the trajectories of ``b``, ``[N_a]``.

    Trajectories are compared as flattened ``[observation, action]`` over the common horizon
    with padded steps set to zero (a length difference therefore counts as distance).
    """
    if a.batch_size[1] != b.batch_size[1]:
        raise ValueError(f"trajectory_distances: horizons differ ({a.batch_size[1]} vs {b.batch_size[1]})")
    fb = _flat_features(b)
    fa = _flat_features(a)
    out = [torch.cdist(fa[i : i + chunk], fb).min(1).values for i in range(0, fa.shape[0], chunk)]
    return torch.cat(out) if out else torch.zeros(0)


def novelty(
    generated: TensorDictBase,
    dataset: TensorDictBase,
    *,
    noise_std: float = 0.1,
    num_perturbed: int | None = None,
    seed: int = 0,
) -> dict[str, torch.Tensor | float]:
    """Novelty of generated trajectories vs a Gaussian-perturbation baseline (paper §4.3).

    The baseline perturbs ``num_perturbed`` random dataset trajectories (default: as many
    as generated) with ``N(0, noise_std)`` on their valid steps; both sets are measured by
    their min L2 distance to the (unperturbed) dataset.

    Returns:
        ``{"generated": [M], "perturbed": [M'], "generated_mean", "perturbed_mean"}``.
    """
    g = torch.Generator().manual_seed(int(seed))
    m = generated.batch_size[0] if num_perturbed is None else int(num_perturbed)
    m = max(1, min(m, dataset.batch_size[0]))
    idx = torch.randperm(dataset.batch_size[0], generator=g)[:m]
    base = dataset[idx].select("observation", "action", "mask").clone()
    mask = base.get("mask")[..., None]
    for key in ("observation", "action"):
        v = base.get(key)
        base.set(key, v + noise_std * torch.randn(v.shape, generator=g).to(v.device) * mask)
    d_gen = trajectory_distances(generated, dataset) if generated.batch_size[0] else torch.zeros(0)
    d_pert = trajectory_distances(base, dataset)
    return {
        "generated": d_gen,
        "perturbed": d_pert,
        "generated_mean": float(d_gen.mean()) if d_gen.numel() else float("nan"),
        "perturbed_mean": float(d_pert.mean()),
    }
