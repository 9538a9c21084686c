"""Goal-conditioned inverse dynamics: the action that takes a state towards the next state of a path.

One model, two uses: :mod:`torchrl_ftb.analysis.tracking` executes a trajectory's state path in closed loop
in the simulator (the tracked reading of the flow's improvement), and the recipe's ``bc.relabel_actions``
gives the flow's generated trajectories actions that their own states call for before behaviour cloning
(:meth:`PathTracker.relabel`; Decision Diffuser likewise acts on its sampled states with inverse dynamics).
Fitted on the dataset's transitions only: offline.
"""
from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import nn
from tqdm.auto import tqdm

#: the observation dimensions a tracker heads for: the hand's position and the gripper's opening
TRACKED_DIMS = (0, 1, 2, 3)


class PathTracker(nn.Module):
    """Goal-conditioned inverse dynamics: ``(o_t, p_{t+1}[dims] - o_t[dims]) -> a_t``, with ``p`` the path.

    An MLP on z-scored inputs (statistics of the transitions it is fitted on, :func:`fit_path_tracker`);
    actions are clipped to ``[-1, 1]``. :meth:`controller` gives the closed-loop form for one path.

    Example:
        >>> tracker = PathTracker(39, 4, hidden=8)
        >>> tracker(torch.zeros(2, 39), torch.zeros(2, 39)).shape
        torch.Size([2, 4])
    """

    def __init__(self, obs_dim: int, action_dim: int, *, hidden: int = 512,
                 dims: tuple[int, ...] = TRACKED_DIMS) -> None:
        super().__init__()
        self.dims = tuple(int(d) for d in dims)
        in_dim = obs_dim + len(self.dims)
        self.net = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, action_dim))
        self.register_buffer("loc", torch.zeros(in_dim))
        self.register_buffer("scale", torch.ones(in_dim))

    def features(self, observation: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        dims = list(self.dims)
        return torch.cat([observation, target[..., dims] - observation[..., dims]], -1)

    def forward(self, observation: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        x = (self.features(observation, target) - self.loc) / self.scale
        return self.net(x).clamp(-1.0, 1.0)

    @torch.no_grad()
    def relabel(self, trajectories: TensorDictBase, rows: torch.Tensor | None = None) -> TensorDictBase:
        """A copy of ``trajectories`` (``[N, H]``) whose ``action`` at each valid step ``t`` heads from ``o_t``
        for ``o_{t+1}`` (the last valid step for itself: hold), on ``rows`` (bool ``[N]``; None: all).

        Example:
            >>> from tensordict import TensorDict
            >>> td = TensorDict({"observation": torch.zeros(2, 3, 39), "action": torch.full((2, 3, 4), 5.0),
            ...                  "mask": torch.ones(2, 3, dtype=torch.bool)}, [2, 3])
            >>> out = PathTracker(39, 4, hidden=4).relabel(td, torch.tensor([True, False]))
            >>> float(out["action"][0].abs().max()) <= 1.0, float(out["action"][1, 0, 0])
            (True, 5.0)
        """
        out = trajectories.clone()
        obs, mask = out.get("observation"), out.get("mask").bool()
        rows = torch.ones(obs.shape[0], dtype=torch.bool) if rows is None else torch.as_tensor(rows, dtype=torch.bool)
        if rows.shape != obs.shape[:1]:
            raise ValueError(f"PathTracker.relabel: rows has shape {list(rows.shape)}, expected [{obs.shape[0]}]")
        # next valid state, or the step itself where the next one is padding (the last valid step: hold)
        nxt = torch.where((mask[:, 1:] & mask[:, :-1])[..., None], obs[:, 1:], obs[:, :-1])
        nxt = torch.cat([nxt, obs[:, -1:]], 1)
        p = next(self.parameters())
        act = self(obs.to(p), nxt.to(p)).to(out.get("action"))
        keep = out.get("action")
        sel = (rows.to(mask.device)[:, None] & mask)[..., None]
        out.set("action", torch.where(sel, act, keep))
        return out

    def controller(self, path: np.ndarray, length: int):
        """``obs -> action`` heading, at its ``t``-th call, for ``path[min(t + 1, length - 1)]`` (then it holds
        the path's last state). The MLP runs in numpy: one small call per simulator step."""
        if length < 1:
            raise ValueError(f"PathTracker.controller: a path needs at least one step, got length {length}")
        layers = [m for m in self.net if isinstance(m, nn.Linear)]
        weights = [(m.weight.detach().double().cpu().numpy().T, m.bias.detach().double().cpu().numpy())
                   for m in layers]
        loc, scale = self.loc.double().cpu().numpy(), self.scale.double().cpu().numpy()
        dims, path, step = list(self.dims), np.asarray(path, dtype=np.float64), [0]

        def act(obs: np.ndarray) -> np.ndarray:
            target = path[min(step[0] + 1, length - 1)]
            step[0] += 1
            h = (np.concatenate([obs, target[dims] - obs[dims]]) - loc) / scale
            for i, (w, b) in enumerate(weights):
                h = h @ w + b
                if i < len(weights) - 1:
                    h = np.maximum(h, 0.0)
            return np.clip(h, -1.0, 1.0)

        return act


def fit_path_tracker(data: TensorDictBase, *, steps: int = 4000, batch_size: int = 1024, lr: float = 1e-3,
                     hidden: int = 512, dims: tuple[int, ...] = TRACKED_DIMS, seed: int = 0,
                     progress: bool = False) -> PathTracker:
    """Fit a :class:`PathTracker` by regression on a dataset's transitions (pairs of consecutive valid steps).

    A hand-written loop: an inverse-dynamics regression used only by this analysis, which no torchrl loss
    covers (``BCLoss`` regresses an action on one observation). Seeded: the same data and seed give the
    same tracker.

    Args:
        data: ``[N, H]`` real trajectories (``observation``, ``action``, ``mask``).
        steps, batch_size, lr, hidden: Adam steps on the mean squared action error, its batch, step size
            and the MLP width.
        dims: the observation dimensions the tracker heads for (Meta-World: hand and gripper).
        seed: initialisation and batches.
        progress: a progress bar.

    Example:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"observation": torch.randn(2, 5, 39), "action": torch.rand(2, 5, 4),
        ...                  "mask": torch.ones(2, 5, dtype=torch.bool)}, [2, 5])
        >>> fit_path_tracker(td, steps=2, hidden=8).dims
        (0, 1, 2, 3)
    """
    obs, act, mask = data.get("observation").float().cpu(), data.get("action").float().cpu(), data.get("mask").cpu()
    pair = mask[:, :-1] & mask[:, 1:]
    if not bool(pair.any()):
        raise ValueError("fit_path_tracker: the data have no pair of consecutive valid steps to fit on")
    if max(dims) >= obs.shape[-1]:
        raise ValueError(f"fit_path_tracker: dims {dims} exceed the observation's {obs.shape[-1]} dimensions")
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        tracker = PathTracker(obs.shape[-1], act.shape[-1], hidden=hidden, dims=dims)
        x = tracker.features(obs[:, :-1], obs[:, 1:])[pair]
        y = act[:, :-1][pair].clamp(-1.0, 1.0)
        tracker.loc.copy_(x.mean(0))
        tracker.scale.copy_(x.std(0).clamp_min(1e-6))
        x = (x - tracker.loc) / tracker.scale
        opt = torch.optim.Adam(tracker.net.parameters(), lr=lr)
        for _ in tqdm(range(steps), desc="path tracker", disable=not progress):
            idx = torch.randint(x.shape[0], (min(batch_size, x.shape[0]),))
            loss = (tracker.net(x[idx]) - y[idx]).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    return tracker.eval()
