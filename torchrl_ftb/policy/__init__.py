"""Policy stage: BC actor, behaviour cloning (torchrl ``BCLoss``), evaluation rollouts."""
from torchrl_ftb.policy.actor import (
    ObservationNormalizer,
    SquashedMLP,
    make_bc_actor,
    make_bc_actor_for,
    observation_statistics,
)
from torchrl_ftb.policy.bc import load_bc_checkpoint, make_transition_buffer, train_bc
from torchrl_ftb.policy.evaluate import episode_statistics, evaluate_policy

__all__ = [
    "ObservationNormalizer",
    "SquashedMLP",
    "episode_statistics",
    "evaluate_policy",
    "load_bc_checkpoint",
    "make_bc_actor",
    "make_bc_actor_for",
    "make_transition_buffer",
    "observation_statistics",
    "train_bc",
]
