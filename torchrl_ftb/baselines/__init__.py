"""Baselines stage: BC / 10%BC / TD3+BC / IQL / IQL + r_ψ / OPRL / zero-reward IQL on the same data as FTB."""
from torchrl_ftb.baselines.data import (
    REWARD_KEY,
    make_reward_transforms,
    make_offline_buffer,
    relabel_rewards,
    reward_scale,
    select_top_trajectories,
    zero_reward_module,
)
from torchrl_ftb.baselines.methods import (
    LABEL_METHODS,
    METHODS,
    TRUE_REWARD_METHODS,
    BaselineResult,
    run_baseline,
    train_reward_model,
)
from torchrl_ftb.baselines.networks import action_spec, make_iql_model, make_td3bc_model
from torchrl_ftb.baselines.offline_rl import log_scalars, make_iql_loss, make_td3bc_loss, train_iql, train_td3bc

__all__ = [
    "BaselineResult",
    "LABEL_METHODS",
    "METHODS",
    "TRUE_REWARD_METHODS",
    "run_baseline",
    "train_reward_model",
    "REWARD_KEY",
    "action_spec",
    "log_scalars",
    "make_iql_loss",
    "make_iql_model",
    "make_reward_transforms",
    "make_td3bc_loss",
    "make_td3bc_model",
    "make_offline_buffer",
    "relabel_rewards",
    "reward_scale",
    "select_top_trajectories",
    "train_iql",
    "train_td3bc",
    "zero_reward_module",
]
