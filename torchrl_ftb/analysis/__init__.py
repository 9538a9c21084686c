"""Analysis stage (paper §4.3): improvement, validity (dynamics error), novelty, plots."""
from torchrl_ftb.analysis.metrics import dynamics_error, improvement, novelty, toy_oracle_step, trajectory_distances
from torchrl_ftb.analysis.plots import plot_flow_curves, plot_histograms, save_figure

__all__ = [
    "dynamics_error",
    "improvement",
    "novelty",
    "plot_flow_curves",
    "plot_histograms",
    "save_figure",
    "toy_oracle_step",
    "trajectory_distances",
]
