import torch
from torchrl.envs.utils import check_env_specs

from torchrl_ftb.testing import MetaWorldMockEnv, ToyLineEnv, toy_optimal_return


def test_mock_specs():
    check_env_specs(ToyLineEnv(max_steps=8))
    check_env_specs(MetaWorldMockEnv(max_steps=8))


def test_toy_optimal_policy_closed_form():
    env = ToyLineEnv(max_steps=20)
    env.set_seed(0)
    td = env.rollout(20, policy=lambda td: td.set("action", torch.tensor([1.0, 0.0])))
    assert td["next", "reward"].sum().item() == toy_optimal_return(20)
    assert bool(td["next", "success"].any())
    assert bool(td["next", "truncated"][-1]) and not bool(td["next", "terminated"].any())


def test_toy_termination_when_leaving_band():
    env = ToyLineEnv(max_steps=50)
    td = env.rollout(50, policy=lambda td: td.set("action", torch.tensor([0.0, 1.0])))
    assert bool(td["next", "terminated"][-1]) and td.shape[0] < 50


def test_metaworld_mock_shapes_and_success():
    env = MetaWorldMockEnv(max_steps=200)
    env.set_seed(0)

    def greedy(td):
        obs = td["observation"]
        return td.set("action", torch.cat([((obs[-3:] - obs[:3]) * 20).clamp(-1, 1), torch.zeros(1)]))

    td = env.rollout(200, policy=greedy)
    assert td["observation"].shape[-1] == 39 and td["action"].shape[-1] == 4
    assert bool(td["next", "success"].any())
