"""Dataset generators: Meta-World (IPL recipe) and a name -> generator registry."""
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
    "DatasetGenerator",
    "dataset_generators",
    "dataset_stats",
    "default_cache_dir",
    "format_stats",
    "get_dataset_generator",
    "make_metaworld_dataset",
    "register_dataset_generator",
]
