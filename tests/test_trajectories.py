import json
import os

import pytest
import torch
from tensordict import TensorDict

from torchrl_ftb.data import (
    coarsen_trajectories,
    flat_to_trajectories,
    hold_last_step,
    load_trajectories,
    pad_trajectories,
    refine_trajectories,
    save_trajectories,
    success_streak_fired,
    success_streak_length,
    trajectories_to_flat,
    trajectory_lengths,
    validate_trajectories,
)
from torchrl_ftb.testing import ToyLineEnv, make_toy_dataset, toy_reward


def test_roundtrip_flat_and_padded(toy_data):
    flat = trajectories_to_flat(toy_data)
    assert flat.batch_size[0] == int(trajectory_lengths(toy_data).sum())
    back = flat_to_trajectories(flat)
    assert back.batch_size[0] == toy_data.batch_size[0]
    assert torch.equal(back["mask"], toy_data["mask"][:, : back.batch_size[1]])
    assert torch.equal(back["observation"], toy_data["observation"][:, : back.batch_size[1]])
    assert torch.equal(back["next", "reward"], toy_data["next", "reward"][:, : back.batch_size[1]])


def test_pad_trajectories_matches_lengths(toy_data):
    lengths = trajectory_lengths(toy_data)
    episodes = [toy_data[i, : int(n)].exclude("mask") for i, n in enumerate(lengths[:5])]
    padded = pad_trajectories(episodes, horizon=16)
    assert torch.equal(trajectory_lengths(padded), lengths[:5])
    assert torch.equal(padded["observation"][padded["mask"]], toy_data[:5]["observation"][toy_data[:5]["mask"]])
    with pytest.raises(ValueError, match="exceeds horizon"):
        pad_trajectories(episodes, horizon=2)


def test_toy_dataset_obeys_env_dynamics_and_reward():
    data = make_toy_dataset(num_trajectories=8, horizon=12, seed=3)
    # next observation of step h is the observation of step h+1 on valid steps
    mask = data["mask"]
    both = mask[:, 1:] & mask[:, :-1]
    assert torch.allclose(data["next", "observation"][:, :-1][both], data["observation"][:, 1:][both])
    # positions integrate actions: p' = p + 0.1 a
    step = data["next", "observation"][..., :2] - data["observation"][..., :2]
    assert torch.allclose(step[mask], 0.1 * data["action"][mask], atol=1e-6)
    assert torch.allclose(data["next", "reward"][mask], toy_reward(data["observation"], data["action"])[mask])
    # replaying the first trajectory's actions in the env from its start gives the same rewards
    env = ToyLineEnv(max_steps=12)
    env.reset()
    env._pos = data["observation"][0, 0, :2].clone()
    n = int(mask[0].sum())
    rewards = []
    for h in range(n):
        td = env.step(TensorDict({"action": data["action"][0, h]}, []))
        rewards.append(td["next", "reward"])
    assert torch.allclose(torch.stack(rewards), data["next", "reward"][0, :n], atol=1e-6)
    assert bool(td["next", "done"]) == bool(data["next", "done"][0, n - 1])


def test_toy_quality_orders_returns():
    q = torch.tensor([1.0, 0.5, 0.0, -0.5])
    data = make_toy_dataset(num_trajectories=4, horizon=32, seed=0, quality=q, noise=0.0)
    ret = (data["next", "reward"].squeeze(-1) * data["mask"]).sum(-1)
    assert torch.all(ret[:-1] > ret[1:])
    assert ret[0] == pytest.approx(32.0, abs=1e-4)  # optimal return = horizon


def test_validate_rejects_bad_input(toy_data):
    with pytest.raises(ValueError, match="missing required key 'action'"):
        validate_trajectories(toy_data.exclude("action"), name="bad.npz")
    bad = toy_data.clone()
    bad["observation"][0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        validate_trajectories(bad)
    # NaN on padded steps is ignored (padding is never read)
    ok = toy_data.clone()
    i = int((~ok["mask"]).nonzero()[0, 0])
    j = int((~ok["mask"]).nonzero()[0, 1])
    ok["observation"][i, j, 0] = float("nan")
    validate_trajectories(ok)
    with pytest.raises(ValueError, match="obs_dim=39"):
        validate_trajectories(toy_data, obs_dim=39)
    holes = toy_data.clone()
    holes["mask"][0, 1] = False
    holes["mask"][0, 2] = True
    with pytest.raises(ValueError, match="prefix"):
        validate_trajectories(holes)
    with pytest.raises(ValueError, match="batch_size"):
        validate_trajectories(toy_data[0])


def test_save_load_atomic(tmp_path, toy_data):
    path = save_trajectories(toy_data, tmp_path / "ds", meta={"env": "toy", "seed": 0})
    td, meta = load_trajectories(path)
    assert meta["env"] == "toy" and meta["num_trajectories"] == 64
    assert (td == toy_data).all()
    # a folder without meta.json (interrupted write) is not a dataset
    os.remove(path / "meta.json")
    with pytest.raises(FileNotFoundError, match="meta.json"):
        load_trajectories(path)
    # overwrite in place works and leaves no temp dirs behind
    save_trajectories(toy_data[:3], tmp_path / "ds2")
    save_trajectories(toy_data[:5], tmp_path / "ds2")
    assert load_trajectories(tmp_path / "ds2")[0].batch_size[0] == 5
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    # wrong format version
    m = json.loads((tmp_path / "ds2" / "meta.json").read_text())
    m["format_version"] = 99
    (tmp_path / "ds2" / "meta.json").write_text(json.dumps(m))
    with pytest.raises(ValueError, match="format_version"):
        load_trajectories(tmp_path / "ds2")


def test_save_refuses_invalid_and_leaves_nothing(tmp_path, toy_data):
    bad = toy_data.clone()
    bad["action"][0, 0, 0] = float("inf")
    with pytest.raises(ValueError):
        save_trajectories(bad, tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_success_streak_length_is_the_generators_stop_rule():
    """The first step that completes ``streak`` consecutive valid successes ends the episode; padding
    never counts; without a streak a trajectory keeps its own length (checked against a plain loop)."""
    gen = torch.Generator().manual_seed(0)
    success = torch.rand(64, 30, generator=gen) < 0.7
    lengths = torch.randint(0, 31, (64,), generator=gen)
    mask = torch.arange(30) < lengths[:, None]
    got = success_streak_length(success, mask, streak=4)
    fired = success_streak_fired(success, mask, streak=4)
    for i in range(64):
        run, want, want_fired = 0, int(lengths[i]), False
        for h in range(int(lengths[i])):
            run = run + 1 if bool(success[i, h]) else 0
            if run == 4:
                want, want_fired = h + 1, True
                break
        assert int(got[i]) == want and bool(fired[i]) == want_fired, i
    assert 0 < int(fired.sum()) < 64  # both cases occur
    # successes in the padding do not complete a streak
    assert success_streak_length(torch.ones(1, 6, dtype=torch.bool), torch.arange(6)[None] < 3, streak=4).tolist() == [3]
    # ... nor make the rule fire
    assert success_streak_fired(torch.ones(1, 6, dtype=torch.bool), torch.arange(6)[None] < 3, streak=4).tolist() == [False]
    assert success_streak_fired(torch.ones(1, 6, dtype=torch.bool), torch.arange(6)[None] < 4, streak=4).tolist() == [True]
    with pytest.raises(ValueError, match="streak must be >= 1"):
        success_streak_length(success, mask, streak=0)
    with pytest.raises(ValueError, match="differ in shape"):
        success_streak_length(success[:, :5], mask, streak=2)



@pytest.mark.parametrize("stride", [1, 3, 5])
def test_coarsen_refine_round_trip_keeps_ends_and_obeys_linear_dynamics(stride):
    data = make_toy_dataset(num_trajectories=16, horizon=23, seed=4)
    lengths = trajectory_lengths(data)
    coarse = coarsen_trajectories(data.select("observation", "action", "mask"), stride)
    assert coarse.batch_size[1] == -(-23 // stride)
    assert torch.equal(coarse["mask"].sum(-1), -(-lengths // stride))  # ceil(n / stride) valid steps
    fine = refine_trajectories(coarse, stride, horizon=23)
    n_fine = trajectory_lengths(fine)
    assert bool((n_fine >= lengths).all()) and bool((n_fine < lengths + stride).all())
    rows = torch.arange(16)
    first, last = data["observation"][:, 0], data["observation"][rows, lengths - 1]
    assert torch.equal(fine["observation"][:, 0], first)
    # the last state is reached at (m - 1) * stride and held to the end
    m = coarse["mask"].sum(-1)
    assert torch.allclose(fine["observation"][rows, (m - 1) * stride], last)
    assert torch.allclose(fine["observation"][rows, n_fine - 1], last)
    # positions integrate actions (p' = p + 0.1 a): the window-mean action held along the interpolated path
    # reproduces every full window exactly; stride 1 is the identity on valid steps
    step = fine["observation"][:, 1:, :2] - fine["observation"][:, :-1, :2]
    t = torch.arange(22)
    interior = t.unsqueeze(0) < ((m - 2).clamp(min=0) * stride).unsqueeze(-1)
    assert torch.allclose(step[interior], 0.1 * fine["action"][:, :-1][interior], atol=1e-5)
    if stride == 1:
        valid = data["mask"]
        assert torch.equal(fine["observation"][valid], data["observation"][valid])
        assert torch.equal(fine["action"][valid], data["action"][valid])


def test_coarsen_refine_reject_a_bad_stride(toy_data):
    with pytest.raises(ValueError, match="stride must be >= 1"):
        coarsen_trajectories(toy_data, 0)
    with pytest.raises(ValueError, match="stride must be >= 1"):
        refine_trajectories(toy_data.select("observation", "mask"), 0, horizon=8)


def test_hold_last_step_continues_each_trajectory_with_its_end_state():
    data = make_toy_dataset(num_trajectories=12, horizon=20, seed=2)
    lengths = trajectory_lengths(data)
    assert bool((lengths < 20).any())  # some padding to hold
    held = hold_last_step(data)
    assert bool(held["mask"].all())
    rows, valid = torch.arange(12), data["mask"]
    assert torch.equal(held["observation"][valid], data["observation"][valid])  # the recorded steps unchanged
    assert torch.equal(held["action"][valid], data["action"][valid])
    t = torch.arange(20).unsqueeze(0)
    after = t >= lengths.unsqueeze(-1)
    last_obs = data["observation"][rows, lengths - 1].unsqueeze(1).expand_as(held["observation"])
    assert torch.equal(held["observation"][after], last_obs[after])
    assert bool((held["action"][after] == 0).all())
    # nested keys are held too (the last reward: what the stop-rule fill assumes)
    last_reward = data["next", "reward"][rows, lengths - 1].unsqueeze(1).expand_as(held["next", "reward"])
    assert torch.equal(held["next", "reward"][after], last_reward[after])
    # on the toy's dynamics (p' = p + 0.1 a) a zero action holds the position: the held steps are consistent
    step = held["observation"][:, 1:, :2] - held["observation"][:, :-1, :2]
    assert bool((step[after[:, 1:]] == 0).all())
    empty = data[:2].clone()
    empty["mask"][1] = False
    with pytest.raises(ValueError, match=r"hold_last_step: trajectories \[1\] have no valid step"):
        hold_last_step(empty)
    with pytest.raises(ValueError, match=r"names keys the batch does not have: \['force'\]"):
        hold_last_step(data, zero=("action", "force"))


def test_atomic_directory_survives_a_concurrent_writer(tmp_path, monkeypatch):
    """Two writers of one directory (two runs building one cache entry): when the other's version lands between
    our move of the old one and our swap, it is moved aside in turn and ours lands; no backup is left behind."""
    import torchrl_ftb.data.trajectories as trajectories
    from torchrl_ftb.data.trajectories import atomic_directory

    target = tmp_path / "entry"
    with atomic_directory(target) as tmp:
        (tmp / "x.txt").write_text("old")
    real_replace, raced = os.replace, []

    def replace(src, dst):
        if str(src).endswith(".tmp") and not raced:  # our swap: the other writer's version lands first
            raced.append(True)
            os.makedirs(dst, exist_ok=True)
            with open(os.path.join(dst, "x.txt"), "w") as f:
                f.write("theirs")
        return real_replace(src, dst)

    monkeypatch.setattr(trajectories.os, "replace", replace)
    with atomic_directory(target) as tmp:
        (tmp / "x.txt").write_text("ours")
    assert raced and (target / "x.txt").read_text() == "ours"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["entry"]
