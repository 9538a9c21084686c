"""Policy stage: BC actor, behaviour cloning (torchrl ``BCLoss``), evaluation rollouts, a goal-conditioned inverse-dynamics tracker."""
from torchrl_ftb.policy.actor import (
    ObservationNormalizer,
    SquashedMLP,
    make_bc_actor,
    make_bc_actor_for,
    observation_statistics,
)
from torchrl_ftb.policy.bc import check_bc_options, load_bc_checkpoint, make_transition_buffer, train_bc
from torchrl_ftb.policy.evaluate import check_evaluation_options, check_policy_sections, episode_statistics, evaluate_policy
from torchrl_ftb.policy.inverse_dynamics import TRACKED_DIMS, PathTracker, fit_path_tracker

__all__ = [
    "ObservationNormalizer",
    "PathTracker",
    "TRACKED_DIMS",
    "SquashedMLP",
    "check_bc_options",
    "check_evaluation_options",
    "check_policy_sections",
    "episode_statistics",
    "evaluate_policy",
    "fit_path_tracker",
    "load_bc_checkpoint",
    "make_bc_actor",
    "make_bc_actor_for",
    "make_transition_buffer",
    "observation_statistics",
    "train_bc",
]
