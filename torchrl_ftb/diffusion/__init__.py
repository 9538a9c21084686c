"""Trajectory diffuser stage (FTB §3.1): conditional diffusion over full trajectories.

Public API::

    diffuser = make_diffuser("cpu", obs_dim=..., action_dim=..., horizon=...)
    diffuser.fit_normalizer(dataset_trajectories)
    train_diffuser(diffuser, pair_replay_buffer, steps=2000, lr=1e-3)
    sampler = DiffusionSampler(diffuser, sampler="ddpm", steps=50, guidance=1.2, seed=0)
    td = sampler(TensorDict({"condition": trajs}, batch_size=[B]))   # -> td["sample"]
    save_diffuser(diffuser, path); diffuser = load_diffuser(path)
"""
from torchrl_ftb.diffusion.backbones import DenoiserBackbone, TemporalUnet
from torchrl_ftb.diffusion.condition import TrajectoryEncoder
from torchrl_ftb.diffusion.loss import DiffusionLoss
from torchrl_ftb.diffusion.model import TrajectoryDiffuser
from torchrl_ftb.diffusion.normalizer import TrajectoryNormalizer
from torchrl_ftb.diffusion.presets import PRESETS, get_preset, make_diffuser, parse_overrides, run_settings
from torchrl_ftb.diffusion.process import SAMPLERS, DiffusionProcess
from torchrl_ftb.diffusion.sampler import DiffusionSampler
from torchrl_ftb.diffusion.train import load_diffuser, save_diffuser, train_diffuser

__all__ = [
    "DenoiserBackbone",
    "TemporalUnet",
    "TrajectoryEncoder",
    "DiffusionProcess",
    "SAMPLERS",
    "TrajectoryNormalizer",
    "TrajectoryDiffuser",
    "DiffusionLoss",
    "DiffusionSampler",
    "PRESETS",
    "get_preset",
    "make_diffuser",
    "parse_overrides",
    "run_settings",
    "train_diffuser",
    "save_diffuser",
    "load_diffuser",
]
