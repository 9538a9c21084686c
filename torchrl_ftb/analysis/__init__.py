"""Analysis stage (paper §4.3): improvement, validity (dynamics error), novelty, open-loop replays, plots."""
from torchrl_ftb.analysis.metrics import dynamics_error, improvement, novelty, toy_oracle_step, trajectory_distances
from torchrl_ftb.analysis.plots import plot_flow_curves, plot_histograms, plot_scatter, save_figure
from torchrl_ftb.analysis.replay import (
    match_rows,
    metaworld_state_returns,
    nearest_start,
    open_loop_improvement,
    replay_returns,
    summarize_samples,
)

__all__ = [
    "dynamics_error",
    "improvement",
    "match_rows",
    "metaworld_state_returns",
    "nearest_start",
    "novelty",
    "open_loop_improvement",
    "plot_flow_curves",
    "plot_histograms",
    "plot_scatter",
    "replay_returns",
    "save_figure",
    "summarize_samples",
    "toy_oracle_step",
    "trajectory_distances",
]
