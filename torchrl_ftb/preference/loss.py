"""Bradley–Terry preference loss on trajectory scores (paper Eq. 4, Alg. 2 line 4).

``P[tau1 > tau0] = exp s(tau1) / (exp s(tau0) + exp s(tau1)) = sigmoid(s1 - s0)``; with a
soft label ``y`` (1: ``tau1`` preferred, 0: ``tau0`` preferred, 0.5: tie) the negative
log-likelihood is ``-[y log sigmoid(s1 - s0) + (1 - y) log sigmoid(s0 - s1)]``, computed with
``logsigmoid`` (stable for any score gap). The authors' code instead applied independent
sigmoids to each score and a BCE — not Bradley–Terry; this module does not.

Example:
    >>> import torch
    >>> bradley_terry_nll(torch.zeros(1), torch.zeros(1), torch.ones(1))  # log 2
    tensor([0.6931])
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule
from torchrl.objectives.utils import _reduce

from torchrl_ftb.preference.score import ScoreModel, _prefixed

__all__ = ["BradleyTerryLoss", "bradley_terry_nll", "preference_accuracy"]


def bradley_terry_nll(score0: torch.Tensor, score1: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """Element-wise Bradley–Terry negative log-likelihood with soft labels (1 = ``tau1`` preferred).

    Example:
        >>> import torch
        >>> s0, s1 = torch.tensor([0.0], requires_grad=True), torch.tensor([0.0])
        >>> bradley_terry_nll(s0, s1, torch.tensor([1.0])).sum().backward()
        >>> s0.grad  # d loss / d s0 = sigmoid(s0 - s1) = 0.5: raising the worse score raises the loss
        tensor([0.5000])
    """
    diff = score1 - score0
    label = label.to(diff.dtype)
    return -(label * F.logsigmoid(diff) + (1.0 - label) * F.logsigmoid(-diff))


def preference_accuracy(score0: torch.Tensor, score1: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """Fraction of non-tie pairs (``label != 0.5``) ranked as labelled; NaN if there are none.

    A pair with exactly equal scores counts as wrong.
    """
    decided = label != 0.5
    if not bool(decided.any()):
        return torch.tensor(float("nan"), device=score0.device)
    predicted = (score1 > score0)[decided]
    wanted = (label > 0.5)[decided]
    correct = (predicted == wanted) & (score1 != score0)[decided]
    return correct.float().mean()


class BradleyTerryLoss(LossModule):
    """Bradley–Terry loss of a :class:`ScoreModel` on a preference-label TensorDict ``[M]``.

    Input: ``"tau0"``/``"tau1"`` sub-TensorDicts ``[M, L]`` (``observation``, ``action``,
    ``mask``) and ``"label"`` ``[M]`` in [0, 1] (1 = ``tau1`` preferred, 0.5 = tie).
    Output: ``loss_preference`` (reduced NLL; with an ensemble, the mean of the members'
    losses, so each member is trained on the same pairs) and the non-loss entries
    ``accuracy`` (non-tie pairs, ensemble-mean scores; NaN if all pairs are ties) and
    ``score_gap`` (mean ``|s1 - s0|``, detached).

    The score model is held as a plain sub-module (no target network is needed, so the
    functional-parameter machinery of other torchrl losses is not used).

    Args:
        score_network: the :class:`ScoreModel` to train.

    Keyword Args:
        reduction: ``"mean"`` | ``"sum"`` | ``"none"`` over pairs.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> model = ScoreModel(3, 2, num_cells=8, seed=0)
        >>> def traj():
        ...     return TensorDict({"observation": torch.randn(4, 5, 3), "action": torch.randn(4, 5, 2),
        ...                        "mask": torch.ones(4, 5, dtype=torch.bool)}, [4, 5])
        >>> labels = TensorDict({"tau0": traj(), "tau1": traj(),
        ...                      "label": torch.tensor([1.0, 0.0, 0.5, 1.0])}, [4])
        >>> out = BradleyTerryLoss(model)(labels)
        >>> out["loss_preference"].backward()
        >>> sorted(out.keys())
        ['accuracy', 'loss_preference', 'score_gap']
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            tau0 (NestedKey): first trajectory of each pair. Defaults to ``"tau0"``.
            tau1 (NestedKey): second trajectory of each pair. Defaults to ``"tau1"``.
            label (NestedKey): preference label, 1 = ``tau1`` preferred. Defaults to ``"label"``.
        """

        tau0: NestedKey = "tau0"
        tau1: NestedKey = "tau1"
        label: NestedKey = "label"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_preference", "accuracy", "score_gap"]

    def __init__(self, score_network: ScoreModel, *, reduction: str = "mean") -> None:
        super().__init__()
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"BradleyTerryLoss: unknown reduction {reduction!r}")
        self.score_network = score_network
        self.reduction = reduction
        self._in_keys = None

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def _set_in_keys(self) -> None:
        keys = [self.tensor_keys.label]
        for tau in (self.tensor_keys.tau0, self.tensor_keys.tau1):
            keys += [_prefixed(tau, k) for k in self.score_network.read_keys]
        self._in_keys = keys

    def set_keys(self, **kwargs) -> None:
        super().set_keys(**kwargs)
        self._in_keys = None

    @property
    def in_keys(self):
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    def _pair_scores(self, tau0: TensorDictBase, tau1: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """Members' scores ``[C, M]`` of both sides; one batched pass when the shapes allow."""
        net = self.score_network
        if tau0.batch_size != tau1.batch_size:
            return net.score(tau0, members=True), net.score(tau1, members=True)
        keys = net.read_keys  # the termination flag too, where the stop-rule fill reads it
        both = net.score(torch.cat([tau0.select(*keys, strict=False), tau1.select(*keys, strict=False)], 0),
                         members=True)
        return both.split(tau0.batch_size[0], dim=-1)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        label = tensordict.get(self.tensor_keys.label)
        if label.ndim != 1:
            raise ValueError(f"BradleyTerryLoss: {self.tensor_keys.label!r} must be [M], got {list(label.shape)}")
        s0, s1 = self._pair_scores(tensordict.get(self.tensor_keys.tau0), tensordict.get(self.tensor_keys.tau1))
        nll = bradley_terry_nll(s0, s1, label).mean(0)  # [M]: mean of the members' losses
        loss = _reduce(nll, self.reduction)
        with torch.no_grad():
            m0, m1 = s0.mean(0), s1.mean(0)
            accuracy = preference_accuracy(m0, m1, label)
            gap = (m1 - m0).abs().mean()
        return TensorDict({"loss_preference": loss, "accuracy": accuracy, "score_gap": gap})
