"""Flow stage: flow to better (Alg. 4) — iterative improvement of the top-k trajectories."""
from torchrl_ftb.flow.flow import (
    FlowResult,
    FlowToBetter,
    accepted_gain_stats,
    adaptive_flow_steps,
    check_flow_options,
    clip_actions,
    default_min_length,
    improves,
    masked_true_return,
    masked_true_returns,
    normalized_scores,
    return_summary,
    trajectory_validity,
    true_return_score,
)

__all__ = [
    "FlowResult",
    "FlowToBetter",
    "accepted_gain_stats",
    "adaptive_flow_steps",
    "check_flow_options",
    "clip_actions",
    "default_min_length",
    "improves",
    "masked_true_return",
    "masked_true_returns",
    "normalized_scores",
    "return_summary",
    "trajectory_validity",
    "true_return_score",
]
