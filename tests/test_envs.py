"""Tests of torchrl_ftb.envs: Meta-World / locomotion factories, scores, reward oracles."""
import functools

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_ftb.analysis import dynamics_error
from torchrl_ftb.envs import (
    D4RL_REF_SCORES,
    SuccessInfoReader,
    d4rl_normalized_score,
    locomotion_env_id,
    locomotion_true_reward,
    make_locomotion_env,
    make_metaworld_env,
    make_metaworld_gym_env,
    metaworld_reward_error,
    metaworld_tasks,
    metaworld_true_reward,
    oracle_step,
    scripted_policy,
)


# ---------------------------------------------------------------- cheap (no simulator)
def test_unknown_metaworld_task_lists_valid_tasks():
    with pytest.raises(ValueError, match="button-press-v3"):
        make_metaworld_env("button-press-v2")
    assert "drawer-open-v3" in metaworld_tasks()


def test_success_info_reader_reads_python_floats():
    reader = SuccessInfoReader()
    assert reader({"success": 1.0}, TensorDict())["success"].tolist() == [True]
    assert reader({"success": 0.0}, TensorDict())["success"].tolist() == [False]
    assert reader({}, TensorDict())["success"].dtype == torch.bool  # reset: no info


def test_d4rl_normalized_score_reference_points():
    for name, (lo, hi) in D4RL_REF_SCORES.items():
        score = d4rl_normalized_score(f"{name}-medium-replay-v2", torch.tensor([lo, hi, (lo + hi) / 2]))
        assert torch.allclose(score, torch.tensor([0.0, 100.0, 50.0]), atol=1e-4)
    assert locomotion_env_id("Walker2d-v5") == "Walker2d-v5" and locomotion_env_id("hopper") == "Hopper-v5"
    with pytest.raises(ValueError, match="hopper"):
        d4rl_normalized_score("ant", 1.0)


# ---------------------------------------------------------------- locomotion (MuJoCo)
@pytest.fixture(scope="module")
def hopper_rollout():
    env = make_locomotion_env("hopper", seed=0)
    torch.manual_seed(0)
    return env.rollout(40)


@pytest.mark.integration
def test_locomotion_env_float32_and_oracle_is_exact(hopper_rollout):
    td = hopper_rollout
    assert td["observation"].dtype == torch.float32
    # the observation clips velocities at +-10: the oracle is exact where they are inside
    ok = td["observation"].abs().amax(-1) < 9.99
    assert ok.sum() >= 5
    nxt = oracle_step("hopper", td["observation"][ok], td["action"][ok])
    assert torch.allclose(nxt, td["next", "observation"][ok], atol=1e-4)
    reward = locomotion_true_reward("hopper", td["observation"][ok], td["action"][ok])
    assert torch.allclose(reward, td["next", "reward"][ok], atol=1e-4)


@pytest.mark.integration
def test_dynamics_error_zero_on_real_data_and_positive_on_corrupted(hopper_rollout):
    td = hopper_rollout
    ok = td["observation"].abs().amax(-1) < 9.99
    n = int(ok.long().cumprod(0).sum())  # prefix of steps with in-range velocities
    traj = td[:n].unsqueeze(0).clone()
    traj["mask"] = torch.ones(1, n, dtype=torch.bool)
    oracle = functools.partial(oracle_step, "hopper")
    err = dynamics_error(traj, oracle)["per_step"]
    assert err.shape == (1, n) and float(err.max()) < 1e-4
    bad = traj.clone()
    bad["next", "observation"] = bad["next", "observation"] + 0.1
    assert abs(dynamics_error(bad, oracle)["mean"] - 0.1) < 1e-3
    with pytest.raises(ValueError, match="observation"):
        oracle_step("hopper", torch.zeros(3, 5), torch.zeros(3, 3))


# ---------------------------------------------------------------- Meta-World
@pytest.mark.integration
def test_metaworld_env_specs_goal_modes_and_time_limit():
    env = make_metaworld_env("button-press-v3", seed=0, max_episode_steps=6)
    td = env.rollout(10, break_when_any_done=True)
    assert td.batch_size == (6,)  # stops at the time limit
    assert td["observation"].dtype == torch.float32 and td["observation"].shape[-1] == 39
    assert td["next", "success"].dtype == torch.bool and td["next", "success"].shape == (6, 1)
    assert bool(td["next", "truncated"][-1]) and not bool(td["next", "terminated"].any())
    goals = [env.reset()["observation"][-3:] for _ in range(2)]
    assert torch.equal(goals[0], goals[1])  # fixed goal
    renv = make_metaworld_env("button-press-v3", seed=0, max_episode_steps=6, random_goal=True)
    obs = [renv.reset()["observation"][4:7] for _ in range(3)]  # button placement is the random part
    assert not torch.allclose(obs[0], obs[1]) and not torch.allclose(obs[1], obs[2])


def test_parallel_metaworld_envs_draw_different_goals_and_a_reseed_repeats_them():
    """``set_seed`` seeds the goal draws: the sub-envs of a ``SerialEnv`` (seeded one after another) start from
    different placements (they all drew the same ones, so num_envs=k evaluated num_episodes/k distinct
    episodes), and an env seeded again with its own seed draws what it drew before."""
    from torchrl.envs import SerialEnv

    make = functools.partial(make_metaworld_env, "button-press-v3", seed=1000, max_episode_steps=5, random_goal=True)
    serial = SerialEnv(2, make)
    serial.set_seed(1000)
    first = serial.reset()["observation"][:, 4:7]
    assert not torch.allclose(first[0], first[1])
    env = make()
    placements = []
    for _ in range(2):
        env.set_seed(1000)
        placements.append(torch.stack([env.reset()["observation"][4:7] for _ in range(3)]))
    assert torch.equal(placements[0], placements[1]) and not torch.allclose(placements[0][0], placements[0][1])
    serial.close()


@pytest.mark.integration
@pytest.mark.parametrize("policy_task", ["door-open-v3", "door-close-v3"])
def test_scripted_policies_leave_the_observation_alone(policy_task):
    """Meta-World's door policies shift parsed positions in place; recorded observations of a
    cross-env episode must still be the env's (the frame stack stays exact)."""
    from torchrl_ftb.envs import metaworld_frame_stack_error

    env = make_metaworld_gym_env("button-press-v3", seed=0, random_goal=True)
    pi = scripted_policy(policy_task)
    obs, _ = env.reset()
    recorded = []
    for _ in range(20):
        recorded.append(obs)
        before = obs.copy()
        obs, *_ = env.step(np.clip(pi(obs), -1 + 1e-5, 1 - 1e-5))
        assert np.array_equal(recorded[-1], before)
    td = TensorDict({"observation": torch.tensor(np.array(recorded), dtype=torch.float32)[None],
                     "mask": torch.ones(1, 20, dtype=torch.bool)}, [1, 20])
    assert float(metaworld_frame_stack_error(td)[0]) < 1e-6


@pytest.fixture(scope="module")
def button_press_episode():
    """A noiseless scripted-expert episode of button-press (raw gymnasium loop, fast)."""
    env = make_metaworld_gym_env("button-press-v3", seed=3, random_goal=True)
    pi = scripted_policy("button-press-v3")
    obs, _ = env.reset()
    rows = []
    for _ in range(120):
        a = np.clip(pi(obs), -1 + 1e-5, 1 - 1e-5)
        nxt, r, _, _, info = env.step(a)
        rows.append((obs, a, nxt, r, info["success"]))
        obs = nxt
    o, a, n, r, s = (np.array(x) for x in zip(*rows))
    h = len(r)
    return TensorDict(
        {"observation": torch.tensor(o, dtype=torch.float32)[None], "action": torch.tensor(a, dtype=torch.float32)[None],
         "mask": torch.ones(1, h, dtype=torch.bool),
         "next": {"observation": torch.tensor(n, dtype=torch.float32)[None],
                  "reward": torch.tensor(r, dtype=torch.float32)[None, :, None],
                  "success": torch.tensor(s > 0)[None, :, None]}},
        batch_size=[1, h],
    )


@pytest.mark.integration
def test_scripted_expert_succeeds(button_press_episode):
    assert bool(button_press_episode["next", "success"].any())


@pytest.mark.integration
def test_metaworld_true_reward_matches_env_on_real_transitions(button_press_episode):
    td = button_press_episode
    err = metaworld_reward_error("button-press-v3", td)
    assert err["reward_mae"] < 0.05 and err["return_rel_mae"] < 0.02
    assert err["success_agreement"] > 0.98
    # shifted observations (what a generated trajectory provides) are nearly as good
    assert metaworld_reward_error("button-press-v3", td, use_next_observation=False)["reward_mae"] < 0.05
    # a trajectory whose hand stays away from the button earns less than the expert
    far = td.clone()
    for key in ("observation", ("next", "observation")):
        far[key][..., 0:3] = far[key][0, 0, 0:3]  # hand frozen at its start
    r_far, s_far = metaworld_true_reward("button-press-v3", far["observation"], far["action"],
                                         next_observation=far["next", "observation"])
    r_true, _ = metaworld_true_reward("button-press-v3", td["observation"], td["action"],
                                      next_observation=td["next", "observation"])
    assert r_far.sum() < 0.5 * r_true.sum()
    # a padded batch (mask) is scored as each valid prefix alone: the shifted next observation of the last
    # valid step is its own, never the padding
    length = 50
    padded = td.select("observation", "action").clone()
    padded["observation"][:, length:] = 0.0
    two = torch.cat([td.select("observation", "action"), padded], 0)
    mask = torch.stack([td["mask"][0], torch.arange(td.shape[1]) < length])
    r_two, s_two = metaworld_true_reward("button-press-v3", two["observation"], two["action"], mask=mask)
    r_alone, s_alone = metaworld_true_reward("button-press-v3", td["observation"][0, :length], td["action"][0, :length])
    r_full, _ = metaworld_true_reward("button-press-v3", td["observation"], td["action"])
    assert torch.equal(r_two[1, :length], r_alone) and torch.equal(s_two[1, :length], s_alone)
    assert torch.equal(r_two[0], r_full[0]) and not bool(r_two[1, length:].any())
    with pytest.raises(ValueError, match="observation"):
        metaworld_true_reward("button-press-v3", torch.zeros(3, 38), torch.zeros(3, 4))


@pytest.mark.integration
def test_metaworld_true_reward_accepts_out_of_range_gripper(button_press_episode):
    """Generated observations may put the gripper opening (obs[3], obs[21]) outside the [0, 1]
    that Meta-World's observation guarantees; the helper projects it back instead of letting
    Meta-World's ``hamacher_product`` raise."""
    td = button_press_episode
    wide, clipped = td.clone(), td.clone()
    for key in ("observation", ("next", "observation")):
        wide[key][..., [3, 21]] = 1.4
        clipped[key][..., [3, 21]] = 1.0
    r_wide, s_wide = metaworld_true_reward("button-press-v3", wide["observation"], wide["action"],
                                           next_observation=wide["next", "observation"])
    r_clip, s_clip = metaworld_true_reward("button-press-v3", clipped["observation"], clipped["action"],
                                           next_observation=clipped["next", "observation"])
    assert torch.equal(r_wide, r_clip) and torch.equal(s_wide, s_clip)


@pytest.mark.integration
def test_hand_model_and_contact_reach_on_real_steps():
    """The linear one-step hand model: ~mm residual on held-out real Meta-World steps, and a hand
    path jittered by 1 cm per step (what an inconsistent generated trajectory looks like) far above;
    an object moved with the hand away counts as contactless motion, far above any real episode's."""
    from torchrl_ftb.envs import (fit_metaworld_contact_reach, fit_metaworld_hand_model,
                                  metaworld_contactless_object_path, metaworld_hand_model_error)

    rng = np.random.default_rng(0)
    episodes = []
    for seed in range(4):
        env = make_metaworld_gym_env("button-press-v3", seed=seed, random_goal=True)
        pi = scripted_policy("button-press-v3")
        obs, _ = env.reset()
        o, a = [], []
        for _ in range(60):
            act = np.clip(pi(obs) + rng.normal(0, 0.5, 4), -1, 1)
            o.append(obs), a.append(act)
            obs, *_ = env.step(act)
        episodes.append((np.array(o), np.array(a)))
    td = TensorDict({"observation": torch.tensor(np.stack([e[0] for e in episodes]), dtype=torch.float32),
                     "action": torch.tensor(np.stack([e[1] for e in episodes]), dtype=torch.float32),
                     "mask": torch.ones(4, 60, dtype=torch.bool)}, [4, 60])
    w = fit_metaworld_hand_model(td[:3])
    held_out = float(metaworld_hand_model_error(td[3:], w)[0])
    assert held_out < 0.003
    jittered = td[3:].clone()
    jittered["observation"][..., 0:3] += 0.01 * torch.randn(1, 60, 3, generator=torch.Generator().manual_seed(0))
    assert float(metaworld_hand_model_error(jittered, w)[0]) > 5 * held_out + 0.005
    # the hand's reach: the button moves only when the hand presses it, a few cm from its reference point
    reach = fit_metaworld_contact_reach(td)
    assert 0.01 < reach < 0.2
    real_max = float(metaworld_contactless_object_path(td, reach).max())
    pressed_from_afar = td[3:].clone()  # the button travels 10 cm while the hand stays where it started
    pressed_from_afar["observation"][..., 0:3] = pressed_from_afar["observation"][:, :1, 0:3]
    pressed_from_afar["observation"][..., 5] += torch.linspace(0, 0.1, 60)
    assert float(metaworld_contactless_object_path(pressed_from_afar, reach)[0]) > real_max + 0.05
    with pytest.raises(ValueError, match="39"):
        metaworld_hand_model_error(TensorDict({"observation": torch.zeros(1, 3, 11), "action": torch.zeros(1, 3, 4),
                                               "mask": torch.ones(1, 3, dtype=torch.bool)}, [1, 3]), w)


def test_hand_steps_count_only_consecutive_valid_steps():
    """metaworld_hand_steps (bench/hand_paths.py, flow.max_hand_step): per-step hand displacement, masked
    where either end is padding, so a padded jump is neither a step nor a trajectory's largest."""
    from torchrl_ftb.envs import metaworld_hand_steps, metaworld_max_hand_step

    obs = torch.zeros(1, 4, 39)
    obs[0, :, 0] = torch.tensor([0.0, 0.003, 0.007, 0.5])  # the last step is padding
    td = TensorDict({"observation": obs, "mask": torch.tensor([[True, True, True, False]])}, [1, 4])
    step, pair = metaworld_hand_steps(td)
    assert pair.tolist() == [[True, True, False]]
    assert step[pair].tolist() == pytest.approx([0.003, 0.004], abs=1e-7)
    assert metaworld_max_hand_step(td).tolist() == pytest.approx([0.004], abs=1e-7)
