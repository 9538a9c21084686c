"""Tests of the name -> env / dataset / true reward / score wiring (torchrl_ftb.envs.factory,
torchrl_ftb.datasets.factory) that the recipes share."""
import functools

import pytest
import torch
from omegaconf import OmegaConf

from torchrl_ftb.data import validate_trajectories
from torchrl_ftb.datasets import dataset_kwargs, make_dataset
from torchrl_ftb.envs import (
    check_env_matches,
    env_kind,
    make_env,
    normalized_score_fn,
    true_reward_fn,
)


def _dims(env) -> tuple[int, int]:
    return int(env.observation_spec["observation"].shape[-1]), int(env.action_spec.shape[-1])


def test_env_kind_of_each_family_and_unknown_names():
    assert env_kind("toy") == "toy"
    assert env_kind("button-press-v3") == "metaworld"
    assert env_kind("hopper") == env_kind("Walker2d-v5") == env_kind("halfcheetah") == "locomotion"
    for bad in ("no-such-task-v3", "button-press-v2", "ant"):
        with pytest.raises(ValueError, match=r"unknown env .*'toy'.*hopper.*button-press-v3"):
            env_kind(bad)
    with pytest.raises(ValueError, match="unknown env"):
        make_env("ant", seed=0)


def test_toy_env_dataset_and_true_reward_agree():
    td, meta = make_dataset("toy", num_trajectories=6, horizon=12, seed=1)
    assert meta["env_id"] == "toy" and meta["path"] is None and td.batch_size == (6, 12)
    env = make_env("toy", seed=0, toy_horizon=12)
    assert _dims(env) == (td["observation"].shape[-1], td["action"].shape[-1])
    assert check_env_matches(functools.partial(make_env, "toy", seed=0), td, name="toy") == (3, 2)
    # the true reward reproduces the dataset's rewards on valid steps, and an env rollout's
    mask = td["mask"]
    reward = true_reward_fn("toy")(td["observation"], td["action"])
    assert reward.shape == td["next", "reward"].shape
    torch.testing.assert_close(reward[mask], td["next", "reward"][mask])
    rollout = env.rollout(12)
    torch.testing.assert_close(true_reward_fn("toy")(rollout["observation"], rollout["action"]),
                               rollout["next", "reward"])
    assert normalized_score_fn("toy") is None and normalized_score_fn("button-press-v3") is None


def test_make_dataset_option_errors():
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['episodes_per_group'\].*num_trajectories"):
        make_dataset("toy", episodes_per_group=3)
    with pytest.raises(ValueError, match="locomotion datasets only"):
        make_dataset("toy", kind="medium")
    with pytest.raises(ValueError, match="needs kind="):
        make_dataset("hopper")
    with pytest.raises(ValueError, match="needs kind="):
        make_dataset("hopper", kind="expert")
    with pytest.raises(ValueError, match="unknown env 'no-such-task-v3'"):
        make_dataset("no-such-task-v3")


def test_dataset_kwargs_picks_each_familys_keys():
    section = OmegaConf.create({"seed": 3, "cache_dir": None, "num_trajectories": 8, "horizon": 16,
                                "episodes_per_group": 2, "noise": 0.5, "num_workers": 1,
                                "options": {"kind": "medium-replay", "num_transitions": None}})
    assert dataset_kwargs("toy", section, max_episode_steps=500, progress=False) == {
        "seed": 3, "cache_dir": None, "progress": False, "num_trajectories": 8, "horizon": 16}
    mw = dataset_kwargs("button-press-v3", section, max_episode_steps=20)
    assert mw["max_steps"] == 20 and mw["episodes_per_group"] == 2 and "horizon" not in mw
    loco = dataset_kwargs("hopper", section, max_episode_steps=500)
    assert loco["kind"] == "medium-replay" and "max_steps" not in loco and "noise" not in loco


def test_normalized_score_is_d4rl_for_locomotion():
    fn = normalized_score_fn("hopper")
    assert fn(3234.3) == pytest.approx(100.0) and fn(-20.272305) == pytest.approx(0.0, abs=1e-4)
    assert isinstance(fn(1000.0), float)


@pytest.mark.integration
def test_metaworld_env_matches_its_dataset(tmp_path):
    td, meta = make_dataset("button-press-v3", episodes_per_group=1, noise=0.0, max_steps=10,
                            cache_dir=tmp_path, progress=False)
    validate_trajectories(td, name="tiny metaworld")
    assert td.batch_size == (4, 10) and meta["path"].startswith(str(tmp_path))
    env = make_env("button-press-v3", seed=0, max_episode_steps=10)
    assert _dims(env) == (td["observation"].shape[-1], td["action"].shape[-1]) == (39, 4)
    rollout = env.rollout(20)
    assert rollout.shape == (10,) and ("next", "success") in rollout.keys(True)
    env.close()
    reward = true_reward_fn("button-press-v3")(td["observation"][0], td["action"][0])
    assert reward.shape == (10, 1)
    # the same simulator pass with its success flags (the flow's stop-rule cut)
    again, success = true_reward_fn("button-press-v3", with_success=True)(td["observation"][0], td["action"][0])
    assert torch.equal(again, reward) and success.shape == (10, 1) and success.dtype == torch.bool
    with pytest.raises(ValueError, match="only Meta-World envs have a per-step success signal"):
        true_reward_fn("toy", with_success=True)


@pytest.mark.integration
def test_locomotion_true_reward_matches_hopper_rollout():
    env = make_env("Hopper-v5", seed=0, max_episode_steps=6)
    torch.manual_seed(0)
    rollout = env.rollout(20)
    env.close()
    assert rollout.shape == (6,)  # the StepCounter limit
    reward = true_reward_fn("hopper")(rollout["observation"], rollout["action"])
    torch.testing.assert_close(reward, rollout["next", "reward"], atol=1e-4, rtol=0)


@pytest.mark.integration
def test_metaworld_evaluation_episodes_differ():
    """Evaluation resets draw new goals: a deterministic policy does not replay one episode."""
    from torchrl_ftb.envs import make_env

    env = make_env("button-press-v3", seed=1000, max_episode_steps=3)
    starts = [env.reset()["observation"].clone() for _ in range(3)]
    assert not torch.allclose(starts[0], starts[1]) or not torch.allclose(starts[1], starts[2])
    fixed = make_env("button-press-v3", seed=1000, max_episode_steps=3, random_goal=False)
    a, b = fixed.reset()["observation"].clone(), fixed.reset()["observation"].clone()
    assert torch.allclose(a, b)
