"""Tests of torchrl_ftb.policy: BC actor, BC training (+ resume), evaluation rollouts."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_ftb.data import trajectories_to_flat
from torchrl_ftb.policy import (
    evaluate_policy,
    load_bc_checkpoint,
    make_bc_actor,
    make_bc_actor_for,
    observation_statistics,
    train_bc,
)
from torchrl_ftb.testing import MetaWorldMockEnv, ToyLineEnv, make_toy_dataset, toy_optimal_return

pytestmark = [pytest.mark.filterwarnings("ignore::UserWarning"), pytest.mark.usefixtures("one_thread")]
H = 16


def _expert_transitions(n: int = 64) -> TensorDict:
    td = make_toy_dataset(num_trajectories=n, horizon=H, seed=0, quality=torch.ones(n), noise=0.1)
    return trajectories_to_flat(td).select("observation", "action")


def _toy_actor(flat: TensorDict, seed: int = 0):
    torch.manual_seed(seed)
    loc, scale = observation_statistics(flat["observation"])
    return make_bc_actor(3, 2, hidden=(64, 64), obs_loc=loc, obs_scale=scale)


def test_bc_on_expert_data_reaches_near_optimal_return():
    flat = _expert_transitions()
    actor = _toy_actor(flat)
    make_env = lambda: ToyLineEnv(max_steps=H)  # noqa: E731
    before = evaluate_policy(make_env, actor, num_episodes=4, seed=1, max_steps=H)
    train_bc(actor, flat, steps=300, batch_size=256, lr=1e-3, weight_decay=0.0, progress=False)
    after = evaluate_policy(make_env, actor, num_episodes=4, seed=1, max_steps=H)
    assert after["return_mean"] >= 0.9 * toy_optimal_return(H)
    assert after["return_mean"] > before["return_mean"] + 5.0
    assert after["success_rate"] == 1.0


def test_actor_is_bounded_and_stores_normalizer():
    actor = make_bc_actor(3, 2, hidden=(8,), obs_loc=torch.ones(3), obs_scale=2 * torch.ones(3), squash="clip")
    out = actor(TensorDict({"observation": 100 * torch.randn(32, 3)}, [32]))
    assert out["action"].abs().max() <= 1.0
    sd = actor.state_dict()
    assert torch.equal(sd["module.normalizer.scale"], 2 * torch.ones(3))
    with pytest.raises(ValueError, match="obs_dim"):
        make_bc_actor(3, 2, obs_loc=torch.zeros(4))
    with pytest.raises(ValueError, match="squash"):
        make_bc_actor(3, 2, squash="relu")


def test_actor_for_a_transition_set_takes_its_size_and_z_score():
    data = TensorDict({"observation": 3 + 2 * torch.randn(64, 5), "action": torch.zeros(64, 2)}, [64])
    other = TensorDict({"observation": torch.randn(16, 5)}, [16])
    actor = make_bc_actor_for(data, hidden=(8,))
    loc, scale = observation_statistics(data["observation"])
    assert torch.equal(actor.module.normalizer.loc, loc) and torch.equal(actor.module.normalizer.scale, scale)
    assert actor(data.select("observation"))["action"].shape == (64, 2)
    # the z-score of another set (e.g. the whole dataset) when asked
    assert torch.equal(make_bc_actor_for(data, statistics_from=other).module.normalizer.loc, other["observation"].mean(0))
    with pytest.raises(ValueError, match="flat"):
        make_bc_actor_for(data.reshape(8, 8))
    with pytest.raises(ValueError, match="no 'action'"):
        make_bc_actor_for(other)


class _GoalReacher(torch.nn.Module):
    """Scripted policy for MetaWorldMockEnv: move the hand (obs[0:3]) towards the goal (obs[-3:])."""

    def forward(self, obs):
        delta = ((obs[..., -3:] - obs[..., 0:3]) / 0.05).clamp(-1, 1)
        return torch.cat([delta, torch.zeros_like(delta[..., :1])], -1)


def test_evaluation_reports_success_on_metaworld_mock():
    reacher = TensorDictModule(_GoalReacher(), ["observation"], ["action"])
    make_env = lambda: MetaWorldMockEnv(max_steps=30)  # noqa: E731
    full = evaluate_policy(make_env, reacher, num_episodes=4, seed=0, max_steps=30)
    early = evaluate_policy(make_env, reacher, num_episodes=4, seed=0, max_steps=30, stop_on_success=True)
    assert full["success_rate"] == 1.0 and early["success_rate"] == 1.0
    assert early["length_mean"] < full["length_mean"] == 30.0
    # a policy that does not move never succeeds
    idle = TensorDictModule(lambda o: torch.zeros(*o.shape[:-1], 4), ["observation"], ["action"])
    idle_out = evaluate_policy(make_env, idle, num_episodes=3, seed=0, max_steps=30)
    assert idle_out["success_rate"] == 0.0
    # batched evaluation counts the requested number of episodes and agrees on success
    batched = evaluate_policy(make_env, reacher, num_episodes=3, seed=0, max_steps=30, num_envs=2,
                              stop_on_success=True, normalized_score_fn=lambda r: 100 * r)
    assert batched["num_episodes"] == 3 and batched["success_rate"] == 1.0
    assert batched["normalized_score"] == pytest.approx(100 * batched["return_mean"], rel=1e-5)


def test_stop_on_success_requires_success_key():
    from torchrl.envs.libs.gym import GymEnv  # noqa: F401  (import cost only)
    from torchrl.testing.mocking_classes import ContinuousActionVecMockEnv

    actor = make_bc_actor(7, 7, hidden=(4,))
    with pytest.raises(ValueError, match="success"):
        evaluate_policy(ContinuousActionVecMockEnv, actor, num_episodes=1, max_steps=2, stop_on_success=True)


def test_bc_checkpoint_resume_and_errors(tmp_path):
    flat = _expert_transitions(16)
    ckpt = tmp_path / "bc.pt"
    actor = _toy_actor(flat)
    train_bc(actor, flat, steps=20, batch_size=32, progress=False, checkpoint_path=ckpt, checkpoint_every=10)
    saved = torch.load(ckpt, weights_only=True)
    assert saved["step"] == 20
    resumed = _toy_actor(flat, seed=1)
    out = train_bc(resumed, flat, steps=30, batch_size=32, progress=False, checkpoint_path=ckpt, resume=True)
    assert out["start_step"] == 20 and torch.load(ckpt, weights_only=True)["step"] == 30
    # a checkpoint for another architecture is refused, the file is left alone
    other = make_bc_actor(3, 2, hidden=(8,))
    before = ckpt.read_bytes()
    with pytest.raises(ValueError, match="does not match"):
        train_bc(other, flat, steps=40, batch_size=32, progress=False, checkpoint_path=ckpt, resume=True)
    assert ckpt.read_bytes() == before
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="corrupt"):
        load_bc_checkpoint(bad, actor)


def test_bc_rejects_bad_transitions():
    actor = make_bc_actor(3, 2, hidden=(4,))
    with pytest.raises(ValueError, match="action"):
        train_bc(actor, TensorDict({"observation": torch.zeros(4, 3)}, [4]), steps=1, progress=False)
    with pytest.raises(ValueError, match=r"\[T\]"):
        train_bc(actor, make_toy_dataset(num_trajectories=2, horizon=4), steps=1, progress=False)


@pytest.mark.parametrize("kwargs, message", [({"steps": -1}, "steps must be >= 0"),
                                             ({"batch_size": 0}, "batch_size must be >= 1"),
                                             ({"lr": 0.0}, "lr must be > 0"),
                                             ({"weight_decay": -1e-3}, "weight_decay must be >= 0"),
                                             ({"steps": "many"}, "steps must be a number, got 'many'"),
                                             ({"lr": None}, "lr must be a number, got None"),
                                             ({"batch_size": 8.5}, "batch_size must be a whole number, got 8.5")])
def test_bc_refuses_bad_numbers_before_touching_data(kwargs, message):
    actor = make_bc_actor(3, 2, hidden=(4,))
    before = [p.clone() for p in actor.parameters()]
    with pytest.raises(ValueError, match=f"train_bc: {message}"):
        train_bc(actor, TensorDict({"observation": torch.zeros(4, 3), "action": torch.zeros(4, 2)}, [4]),
                 progress=False, **{"steps": 1, **kwargs})
    assert all(torch.equal(a, b) for a, b in zip(before, actor.parameters()))


@pytest.mark.parametrize("name", ["num_episodes", "num_envs", "max_steps"])
def test_evaluate_refuses_bad_numbers_before_building_an_env(name):
    def no_env():
        raise AssertionError("the env must not be built")

    with pytest.raises(ValueError, match=f"evaluate_policy: {name} must be >= 1, got 0"):
        evaluate_policy(no_env, make_bc_actor(3, 2, hidden=(4,)), **{name: 0})
    with pytest.raises(ValueError, match=f"evaluate_policy: {name} must be a number, got 'ten'"):
        evaluate_policy(no_env, make_bc_actor(3, 2, hidden=(4,)), **{name: "ten"})
    for value in (10.5, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=f"evaluate_policy: {name} must be a whole number, got {value}"):
            evaluate_policy(no_env, make_bc_actor(3, 2, hidden=(4,)), **{name: value})


def test_evaluate_without_max_steps_runs_each_episode_to_the_env_s_own_end():
    """``max_steps=None`` (the recipes' default ``eval.max_steps: null``): every episode runs until the env ends it,
    so a locomotion episode is not cut at a Meta-World 500; a number still caps it."""
    actor = make_bc_actor(ToyLineEnv().observation_spec["observation"].shape[-1], 2, hidden=(4,))
    own = evaluate_policy(lambda: ToyLineEnv(max_steps=37), actor, num_episodes=2, seed=0, max_steps=None)
    capped = evaluate_policy(lambda: ToyLineEnv(max_steps=37), actor, num_episodes=2, seed=0, max_steps=10)
    assert own["length_mean"] == 37 and capped["length_mean"] == 10
    # a config's whole floats are counts (the recipes pass ``eval.max_steps`` as they read it)
    floats = evaluate_policy(lambda: ToyLineEnv(max_steps=37), actor, num_episodes=2.0, num_envs=2.0, seed=0,
                             max_steps=10.0)
    assert floats["length_mean"] == 10 and floats["num_episodes"] == 2
