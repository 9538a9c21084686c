"""Data stage: padded trajectory batches, persistence, loaders and preference labels."""
from torchrl_ftb.data.trajectories import (
    FORMAT_VERSION,
    atomic_torch_save,
    atomic_write_text,
    flat_to_trajectories,
    load_trajectories,
    pad_trajectories,
    save_trajectories,
    trajectories_to_flat,
    trajectory_lengths,
    validate_trajectories,
)

__all__ = [
    "FORMAT_VERSION",
    "atomic_torch_save",
    "atomic_write_text",
    "flat_to_trajectories",
    "load_trajectories",
    "pad_trajectories",
    "save_trajectories",
    "trajectories_to_flat",
    "trajectory_lengths",
    "validate_trajectories",
]
