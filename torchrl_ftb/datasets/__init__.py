"""Dataset generators: Meta-World (IPL recipe), locomotion (own SAC behaviour policies), a name -> generator registry and
:func:`make_dataset`, the one entry point from an env name to its dataset."""
from torchrl_ftb.datasets.factory import dataset_kwargs, make_dataset
from torchrl_ftb.datasets.locomotion import (
    LOCOMOTION_KINDS,
    collect_rollouts,
    export_behavior_policies,
    load_behavior_policy,
    make_locomotion_dataset,
    shipped_policy_path,
)
from torchrl_ftb.datasets.metaworld import (
    GENERATOR_VERSION,
    GROUPS,
    dataset_stats,
    default_cache_dir,
    format_stats,
    make_metaworld_dataset,
)
from torchrl_ftb.datasets.registry import (
    DatasetGenerator,
    dataset_generators,
    get_dataset_generator,
    register_dataset_generator,
)

__all__ = [
    "GENERATOR_VERSION",
    "GROUPS",
    "LOCOMOTION_KINDS",
    "DatasetGenerator",
    "collect_rollouts",
    "export_behavior_policies",
    "load_behavior_policy",
    "make_locomotion_dataset",
    "shipped_policy_path",
    "dataset_generators",
    "dataset_kwargs",
    "dataset_stats",
    "default_cache_dir",
    "format_stats",
    "get_dataset_generator",
    "make_dataset",
    "make_metaworld_dataset",
    "register_dataset_generator",
]
