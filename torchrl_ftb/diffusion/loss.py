"""``DiffusionLoss``: the classifier-free trajectory-diffuser objective (FTB Eq. 3) as a LossModule.

``E_{t, eps, (tau0 -> tau1), beta~Bern(p)} || eps - eps_theta(tau1_t, (1-beta) tau0 + beta null, t) ||^2``

averaged over the supervised entries: state/action (/reward) channels on the target's valid
steps only (every step with the diffuser's ``padding_loss``: the padding's target is 0), the
validity channel on every step (see :mod:`torchrl_ftb.diffusion.model`).

Example:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torchrl_ftb.diffusion import make_diffuser
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> data = make_toy_dataset(num_trajectories=8, horizon=8, seed=0)
    >>> diffuser = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=8).fit_normalizer(data)
    >>> pairs = TensorDict({"condition": data[:4], "target": data[4:]}, batch_size=[4])
    >>> loss = DiffusionLoss(diffuser)(pairs)
    >>> loss["loss_diffusion"].backward()
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from torchrl_ftb.diffusion.model import TrajectoryDiffuser
from torchrl_ftb.preference.score import NORMALIZED_SCORE_KEY

__all__ = ["DiffusionLoss"]


class DiffusionLoss(LossModule):
    """Masked denoising loss with condition dropout, output ``"loss_diffusion"``.

    The regression target is the noise (epsilon prediction, the paper's Eq. 3) or the clean
    trajectory, as the diffuser's ``process.prediction_type`` says.

    Consumes pair batches from the block pair sampler: a TensorDict ``[B]`` with sub-tds
    ``"condition"`` and ``"target"`` ``[B, H]`` (``observation``, ``action``, ``mask`` and
    ``("next", "reward")`` when the model diffuses rewards; the condition's
    ``"normalized_score"`` with ``score_condition``). Also reports (detached, not
    ``loss_``-prefixed) ``"diffusion_mse_data"`` (valid steps, with or without ``padding_loss``) and
    ``"diffusion_mse_validity"``.

    Args:
        diffuser: the :class:`TrajectoryDiffuser` to train.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            condition: sub-td of the worse (conditioning) trajectories. Default ``"condition"``.
            target: sub-td of the better (generated) trajectories. Default ``"target"``.
            observation: inside condition/target. Default ``"observation"``.
            action: inside condition/target. Default ``"action"``.
            reward: inside condition/target (only with ``reward_channel``). Default ``("next", "reward")``.
            mask: inside condition/target. Default ``"mask"``.
        """

        condition: NestedKey = "condition"
        target: NestedKey = "target"
        observation: NestedKey = "observation"
        action: NestedKey = "action"
        reward: NestedKey = ("next", "reward")
        mask: NestedKey = "mask"

    default_keys = _AcceptedKeys
    out_keys = ["loss_diffusion"]

    def __init__(self, diffuser: TrajectoryDiffuser) -> None:
        super().__init__()
        self.diffuser = diffuser

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list:
        k = self.tensor_keys
        inner = [k.observation, k.action, k.mask] + ([k.reward] if self.diffuser.reward_channel else [])
        subs = [k.target] if self.diffuser.unconditional else [k.condition, k.target]
        keys = [(*_as_tuple(s), *_as_tuple(i)) for s in subs for i in inner]
        if self.diffuser.score_condition:
            keys.append((*_as_tuple(k.condition), NORMALIZED_SCORE_KEY))
        return keys

    def _unpack(self, td: TensorDictBase, which: str) -> tuple[torch.Tensor, torch.Tensor]:
        k = self.tensor_keys
        sub_key = getattr(k, which)
        if sub_key not in td.keys(include_nested=True):
            raise ValueError(f"DiffusionLoss: batch has no {sub_key!r} sub-tensordict (keys: {list(td.keys())})")
        sub = td.get(sub_key)
        if sub.batch_dims != 2:
            raise ValueError(f"DiffusionLoss: {sub_key!r} must be a trajectory batch [B, H], got {list(sub.batch_size)}")
        for key in (k.observation, k.action, k.mask):
            if key not in sub.keys(include_nested=True):
                raise ValueError(f"DiffusionLoss: {sub_key!r} is missing field {key!r}")
        reward = sub.get(k.reward, None) if self.diffuser.reward_channel else None
        raw = self.diffuser.raw_data(sub.get(k.observation), sub.get(k.action), reward, name=f"DiffusionLoss[{sub_key!r}]")
        return raw, sub.get(k.mask).bool()

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        d = self.diffuser
        raw, mask = self._unpack(tensordict, "target")
        x0 = d.model_input(raw, mask)
        batch = x0.shape[0]
        t = d.process.sample_timesteps(batch, device=x0.device)
        noise = torch.randn_like(x0)
        x_t = d.process.add_noise(x0, noise, t)
        cond_emb = cond_mask = None
        if not d.unconditional:
            craw, cmask = self._unpack(tensordict, "condition")
            score = d.condition_score(tensordict.get(self.tensor_keys.condition), name="DiffusionLoss['condition']")
            drop = torch.rand(batch, device=x0.device) < d.cond_drop_prob
            cond_emb, cond_mask = d.encode_condition(d.condition_input(craw, cmask), cmask, score=score, drop=drop)
        out = d.backbone(x_t, t, cond_emb, cond_mask)
        err = (out.float() - d.process.training_target(x0, noise, t)).pow(2)
        data_err = (err[..., :-1] * mask[..., None]).sum()  # valid steps
        valid_err = err[..., -1].sum()
        n_data = mask.sum() * d.diffused_dim
        if d.padding_loss:  # the data channels on padded steps too
            pad_err, n_pad = (err[..., :-1] * ~mask[..., None]).sum(), (~mask).sum() * d.diffused_dim
        else:
            pad_err, n_pad = err.new_zeros(()), 0
        loss = (data_err + pad_err + valid_err) / (n_data + n_pad + mask.numel())
        return TensorDict(
            {
                "loss_diffusion": loss,
                "diffusion_mse_data": (data_err / n_data.clamp(min=1)).detach(),
                "diffusion_mse_validity": (valid_err / mask.numel()).detach(),
            },
            batch_size=[],
        )


def _as_tuple(key: NestedKey) -> tuple:
    return key if isinstance(key, tuple) else (key,)
