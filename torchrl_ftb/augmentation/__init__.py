"""FTB as data augmentation for offline RL (paper §4.4) and the SYNTHETIC baseline."""
from torchrl_ftb.augmentation.augment import (
    AUGMENTATIONS,
    TRANSITION_KEYS,
    as_transitions,
    build_supplement,
    ends_in_termination,
    flow_supplement,
    load_supplement,
    merge_datasets,
    synthetic_supplement,
)

__all__ = [
    "AUGMENTATIONS",
    "TRANSITION_KEYS",
    "as_transitions",
    "build_supplement",
    "ends_in_termination",
    "flow_supplement",
    "load_supplement",
    "merge_datasets",
    "synthetic_supplement",
]
