"""Preference stage: score model, Bradley–Terry loss, K-means blocks, pair samplers, metrics.

Preference augmentation (paper §3.2, Alg. 2): train ``s_psi`` on the labels
(:func:`train_score_model`), score every trajectory (:func:`score_trajectories`), cluster the
scores into ascending blocks (:func:`make_blocks`) and sample adjacent-block pairs for the
diffuser (:func:`make_block_pair_buffer`).
"""
from torchrl_ftb.preference.blocks import BlockWarning, make_blocks
from torchrl_ftb.preference.loss import BradleyTerryLoss, bradley_terry_nll, preference_accuracy
from torchrl_ftb.preference.metrics import (
    correlations,
    pairwise_accuracy,
    plot_preference_scatter,
    preference_metrics,
    top_k_mean,
)
from torchrl_ftb.preference.pairs import (
    BlockPairSampler,
    PairToConditionTarget,
    make_block_pair_buffer,
    make_labeled_pair_buffer,
    make_trajectory_buffer,
    standardized_starts,
)
from torchrl_ftb.preference.queries import QUERY_STRATEGIES, make_query_labels, query_priority, select_queries
from torchrl_ftb.preference.score import (
    NORMALIZED_SCORE_KEY,
    REWARD_ACTIVATIONS,
    SCORE_MODEL_CHECKPOINT,
    ScoreModel,
    load_score_model,
    normalized_scores,
    pessimistic_scores,
    save_score_model,
    score_objective,
    score_trajectories,
    with_normalized_scores,
)
from torchrl_ftb.preference.train import split_labels, train_score_model

__all__ = [
    "NORMALIZED_SCORE_KEY",
    "QUERY_STRATEGIES",
    "REWARD_ACTIVATIONS",
    "BlockPairSampler",
    "BlockWarning",
    "BradleyTerryLoss",
    "PairToConditionTarget",
    "SCORE_MODEL_CHECKPOINT",
    "ScoreModel",
    "bradley_terry_nll",
    "correlations",
    "top_k_mean",
    "make_block_pair_buffer",
    "make_blocks",
    "make_labeled_pair_buffer",
    "make_query_labels",
    "make_trajectory_buffer",
    "standardized_starts",
    "load_score_model",
    "pairwise_accuracy",
    "pessimistic_scores",
    "plot_preference_scatter",
    "preference_accuracy",
    "preference_metrics",
    "query_priority",
    "save_score_model",
    "score_objective",
    "score_trajectories",
    "select_queries",
    "normalized_scores",
    "with_normalized_scores",
    "split_labels",
    "train_score_model",
]
