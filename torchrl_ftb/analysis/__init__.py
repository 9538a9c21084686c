"""Analysis stage (paper §4.3): improvement, validity (dynamics error), novelty, open-loop and tracked replays, plots."""
from torchrl_ftb.analysis.metrics import (
    dynamics_error,
    fit_dynamics_reference,
    improvement,
    novelty,
    per_step_mean,
    toy_oracle_step,
    trajectory_distances,
)
from torchrl_ftb.analysis.plots import plot_curves, plot_flow_curves, plot_histograms, plot_scatter, save_figure
from torchrl_ftb.analysis.replay import (
    ended_early,
    episode_jobs,
    locomotion_open_loop_improvement,
    locomotion_replays,
    match_rows,
    metaworld_state_returns,
    nearest_start,
    open_loop_improvement,
    replay_returns,
    summarize_samples,
)
from torchrl_ftb.analysis.tracking import locomotion_tracked_improvement, track_paths, tracked_improvement

__all__ = [
    "dynamics_error",
    "ended_early",
    "episode_jobs",
    "fit_dynamics_reference",
    "improvement",
    "locomotion_open_loop_improvement",
    "locomotion_replays",
    "locomotion_tracked_improvement",
    "match_rows",
    "metaworld_state_returns",
    "nearest_start",
    "novelty",
    "open_loop_improvement",
    "per_step_mean",
    "plot_curves",
    "plot_flow_curves",
    "plot_histograms",
    "plot_scatter",
    "replay_returns",
    "save_figure",
    "summarize_samples",
    "toy_oracle_step",
    "track_paths",
    "tracked_improvement",
    "trajectory_distances",
]
