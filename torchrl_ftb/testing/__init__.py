"""Mock environments and toy data for tests (TorchRL's mock-env pattern)."""
from torchrl_ftb.testing.mocks import (
    MetaWorldMockEnv,
    ToyLineEnv,
    make_toy_dataset,
    toy_optimal_return,
    toy_reward,
)
from torchrl_ftb.testing.scripts import load_script

__all__ = ["ToyLineEnv", "MetaWorldMockEnv", "make_toy_dataset", "toy_reward", "toy_optimal_return", "load_script"]
