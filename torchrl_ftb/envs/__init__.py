"""Environments: torchrl env factories (Meta-World v3, MuJoCo locomotion), the success info
reader, D4RL normalized scores, ground-truth rewards and the locomotion dynamics oracle, and
the name -> env/true reward/score wiring (``env_kind``, ``make_env``, ``true_reward_fn``,
``normalized_score_fn``)."""
from torchrl_ftb.envs.factory import (
    EnvKind,
    check_env_matches,
    env_kind,
    make_env,
    normalized_score_fn,
    true_reward_fn,
)
from torchrl_ftb.envs.locomotion import (
    D4RL_REF_SCORES,
    LOCOMOTION_ENVS,
    d4rl_normalized_score,
    dynamics_error,
    locomotion_env_id,
    locomotion_true_reward,
    make_locomotion_env,
    oracle_step,
)
from torchrl_ftb.envs.metaworld import (
    METAWORLD_MAX_EPISODE_STEPS,
    SuccessInfoReader,
    check_metaworld_task,
    configure_goal,
    make_metaworld_env,
    make_metaworld_gym_env,
    metaworld_frame_stack_error,
    metaworld_reward_error,
    metaworld_tasks,
    metaworld_true_reward,
    scripted_policy,
)

__all__ = [
    "D4RL_REF_SCORES",
    "EnvKind",
    "LOCOMOTION_ENVS",
    "METAWORLD_MAX_EPISODE_STEPS",
    "SuccessInfoReader",
    "check_env_matches",
    "check_metaworld_task",
    "configure_goal",
    "d4rl_normalized_score",
    "dynamics_error",
    "env_kind",
    "locomotion_env_id",
    "locomotion_true_reward",
    "make_env",
    "make_locomotion_env",
    "make_metaworld_env",
    "make_metaworld_gym_env",
    "metaworld_frame_stack_error",
    "metaworld_reward_error",
    "metaworld_tasks",
    "metaworld_true_reward",
    "normalized_score_fn",
    "oracle_step",
    "scripted_policy",
    "true_reward_fn",
]
