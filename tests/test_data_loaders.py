"""Loaders: own transition files, D4RL (HDF5, torchrl memmap), Minari — on files made here."""

import warnings

import h5py
import numpy as np
import pytest
import torch

from torchrl_ftb.data.loaders import (
    load_d4rl,
    load_d4rl_hdf5,
    load_minari,
    load_transitions_file,
    save_transitions_file,
    transitions_from_arrays,
)
from torchrl_ftb.data.trajectories import trajectory_lengths
from torchrl_ftb.testing import make_toy_dataset


def _d4rl_arrays(seed: int = 0) -> dict:
    """Three episodes in D4RL layout: terminated (4 steps), timed out (5), cut tail (3)."""
    rng = np.random.default_rng(seed)
    t = 12
    obs = rng.normal(size=(t + 1, 4)).astype(np.float32)
    terminals = np.zeros(t, bool)
    timeouts = np.zeros(t, bool)
    terminals[3] = True
    timeouts[8] = True
    return {
        "observations": obs[:-1],
        "next_observations": obs[1:],
        "actions": rng.uniform(-1, 1, size=(t, 2)).astype(np.float32),
        "rewards": rng.normal(size=t).astype(np.float32) + 2.0,
        "terminals": terminals,
        "timeouts": timeouts,
    }


def _write_d4rl_h5(path, arrays: dict, *, metadata: bool = True) -> None:
    with h5py.File(path, "w") as f:
        for k, v in arrays.items():
            f.create_dataset(k, data=v)
        f.create_dataset(
            "infos/qpos", data=np.ones((len(arrays["actions"]), 3))
        )  # D4RL extras, ignored
        if metadata:  # (tensordict's from_h5, used by torchrl, cannot read a scalar-only group)
            f.create_dataset("metadata/algorithm", data="SAC")


def _valid(td, key):
    return td.get(key)[td.get("mask")]


@pytest.mark.parametrize("suffix", [".npz", ".h5"])
def test_transition_file_roundtrip_keeps_values_and_boundaries(tmp_path, suffix):
    trajs = make_toy_dataset(num_trajectories=12, horizon=10, seed=3)
    trajs.set("state", torch.randn(12, 10, 5) * trajs["mask"][..., None])
    path = save_transitions_file(trajs, tmp_path / f"toy{suffix}")
    back = load_transitions_file(path, obs_dim=3, action_dim=2)
    assert torch.equal(trajectory_lengths(back), trajectory_lengths(trajs))
    for key in (
        "observation",
        "action",
        "state",
        ("next", "observation"),
        ("next", "reward"),
        ("next", "terminated"),
        ("next", "truncated"),
        ("next", "done"),
        ("next", "success"),
    ):
        assert torch.equal(_valid(back, key), _valid(trajs, key)), key
    assert "quality" not in back.keys()  # not a format field


def test_unflagged_episode_ends_are_written_as_timeouts(tmp_path):
    trajs = make_toy_dataset(num_trajectories=5, horizon=6, seed=1)
    trajs.set(("next", "truncated"), torch.zeros_like(trajs["next", "truncated"]))
    trajs.set(("next", "terminated"), torch.zeros_like(trajs["next", "terminated"]))
    back = load_transitions_file(save_transitions_file(trajs, tmp_path / "cut.npz"))
    assert back.batch_size[0] == 5  # episodes did not merge
    last = trajectory_lengths(back) - 1
    assert back["next", "truncated"][torch.arange(5), last].all()


def test_missing_next_observations_taken_from_next_row_inside_episodes():
    arrays = _d4rl_arrays()
    del arrays["next_observations"]
    td = transitions_from_arrays(arrays, name="mem")
    assert torch.equal(trajectory_lengths(td), torch.tensor([4, 5, 3]))
    obs = torch.as_tensor(arrays["observations"])
    assert torch.equal(td["next", "observation"][0, :3], obs[1:4])
    assert torch.equal(td["next", "observation"][0, 3], torch.zeros(4))  # unknown at an episode end
    assert torch.equal(td["next", "observation"][1, :4], obs[5:9])


def test_transition_file_errors_name_file_and_field(tmp_path):
    good = _d4rl_arrays()

    def write(name, **changes):
        arrays = {**good, **changes}
        arrays = {k: v for k, v in arrays.items() if v is not None}
        path = tmp_path / name
        np.savez(path, **arrays)
        return path

    with pytest.raises(ValueError, match=r"missing\.npz.*missing required field.*'terminals'"):
        load_transitions_file(write("missing.npz", terminals=None))
    with pytest.raises(
        ValueError, match=r"rows\.npz.*'actions' has 11 rows.*'observations' has 12"
    ):
        load_transitions_file(write("rows.npz", actions=good["actions"][:-1]))
    with pytest.raises(
        ValueError, match=r"nextshape\.npz.*'next_observations' has shape \[12, 3\]"
    ):
        load_transitions_file(
            write("nextshape.npz", next_observations=good["next_observations"][:, :3])
        )
    rewards = good["rewards"].copy()
    rewards[7] = np.nan
    with pytest.raises(
        ValueError, match=r"nan\.npz.*'rewards' has 1 NaN/inf values \(first in row 7\)"
    ):
        load_transitions_file(write("nan.npz", rewards=rewards))
    with pytest.raises(ValueError, match=r"flags\.npz.*'terminals' must be boolean"):
        load_transitions_file(write("flags.npz", terminals=np.full(12, 2.0)))
    with pytest.raises(ValueError, match=r"dim\.npz.*dimension 4 but obs_dim=11"):
        load_transitions_file(write("dim.npz"), obs_dim=11)
    with pytest.raises(ValueError, match="unknown file type"):
        load_transitions_file(write("x.npz").rename(tmp_path / "x.csv"))
    with pytest.raises(FileNotFoundError):
        load_transitions_file(tmp_path / "absent.npz")


def test_load_d4rl_hdf5_splits_on_terminals_and_timeouts(tmp_path):
    arrays = _d4rl_arrays()
    _write_d4rl_h5(tmp_path / "toy.hdf5", arrays)
    td = load_d4rl_hdf5(tmp_path / "toy.hdf5", obs_dim=4, action_dim=2)
    assert torch.equal(trajectory_lengths(td), torch.tensor([4, 5, 3]))
    assert torch.equal(_valid(td, "observation"), torch.as_tensor(arrays["observations"]))
    assert torch.equal(
        _valid(td, ("next", "observation")), torch.as_tensor(arrays["next_observations"])
    )
    assert torch.equal(
        _valid(td, ("next", "reward")).squeeze(-1), torch.as_tensor(arrays["rewards"])
    )
    assert td["next", "terminated"][0, 3] and not td["next", "truncated"][0, 3]
    assert td["next", "truncated"][1, 4] and not td["next", "terminated"][1, 4]
    assert td["next", "truncated"][2, 2]  # the cut tail ends as truncated
    assert torch.equal(td["next", "done"], td["next", "terminated"] | td["next", "truncated"])
    no_reward = {k: v for k, v in arrays.items() if k != "rewards"}
    _write_d4rl_h5(tmp_path / "noreward.hdf5", no_reward)
    with pytest.raises(ValueError, match=r"noreward\.hdf5.*'rewards'"):
        load_d4rl_hdf5(tmp_path / "noreward.hdf5")


@pytest.mark.parametrize("split_trajs", [False, True])
def test_load_d4rl_reads_the_folder_torchrl_builds(tmp_path, monkeypatch, split_trajs):
    """Build ``<root>/<id>`` with torchrl's own D4RL pipeline (download replaced by our file)."""
    import torchrl.data.datasets.d4rl as trl_d4rl
    from torchrl.data.datasets import D4RLExperienceReplay

    arrays = _d4rl_arrays()
    h5 = tmp_path / "toy-v2.hdf5"
    _write_d4rl_h5(h5, arrays, metadata=False)
    monkeypatch.setitem(trl_d4rl.D4RL_DATASETS, "toy-v2", "file:///nowhere/toy-v2.hdf5")
    monkeypatch.setattr(trl_d4rl, "_download_dataset_from_url", lambda url, path: str(h5))
    root = tmp_path / "d4rl"
    D4RLExperienceReplay(
        "toy-v2",
        batch_size=4,
        root=root,
        download=True,
        direct_download=True,
        split_trajs=split_trajs,
    )
    assert (root / "toy-v2").is_dir()

    td = load_d4rl("toy-v2", root=root, obs_dim=4, action_dim=2)
    ref = load_d4rl_hdf5(h5)
    # torchrl drops the file's last transition; everything else is the file's content
    assert torch.equal(trajectory_lengths(td), torch.tensor([4, 5, 2]))
    assert torch.equal(_valid(td, "observation"), _valid(ref, "observation")[:-1])
    assert torch.equal(_valid(td, "action"), _valid(ref, "action")[:-1])
    assert torch.equal(_valid(td, ("next", "reward")), _valid(ref, ("next", "reward"))[:-1])
    assert torch.equal(
        td["next", "terminated"],
        ref["next", "terminated"][:, : td.batch_size[1]] & td["mask"][..., None],
    )
    # torchrl zeroes next observations where the file ends an episode, keeps them elsewhere
    file_done = torch.as_tensor(arrays["terminals"] | arrays["timeouts"])[:-1]
    next_obs = _valid(td, ("next", "observation"))
    assert torch.equal(
        next_obs[~file_done], torch.as_tensor(arrays["next_observations"])[:-1][~file_done]
    )
    assert bool((next_obs[file_done] == 0).all()) and int(file_done.sum()) == 2
    with pytest.raises(FileNotFoundError, match="absent-v2"):
        load_d4rl("absent-v2", root=root)


def test_load_minari_reads_real_values(tmp_path, monkeypatch):
    minari = pytest.importorskip("minari")
    import gymnasium as gym
    from minari.data_collector.episode_buffer import EpisodeBuffer

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    env = gym.make("Pendulum-v1", max_episode_steps=6)
    rng = np.random.default_rng(0)
    buffers, recorded = [], []
    for ep, terminate_at in enumerate([None, 2]):
        obs, _ = env.reset(seed=ep)
        observations, actions, rewards, terms, truncs, success = [obs], [], [], [], [], [False]
        for step in range(6):
            action = rng.uniform(-2, 2, size=1).astype(np.float32)
            obs, reward, _, trunc, _ = env.step(action)
            term = step == terminate_at
            recorded.append((observations[-1], action, reward))
            observations.append(obs)
            actions.append(action)
            rewards.append(reward)
            terms.append(term)
            truncs.append(trunc and not term)
            success.append(bool(reward > -1.0))
            if term or trunc:
                break
        buffers.append(
            EpisodeBuffer(
                id=ep,
                observations=observations,
                actions=actions,
                rewards=rewards,
                terminations=terms,
                truncations=truncs,
                infos={"success": success},
            )
        )
    with warnings.catch_warnings():  # Minari warns about missing author/description metadata
        warnings.simplefilter("ignore")
        minari.create_dataset_from_buffers(
            "test/pendulum/tiny-v0", buffers, env=env, algorithm_name="random"
        )

    by_id = load_minari("test/pendulum/tiny-v0", obs_dim=3, action_dim=1)
    by_path = load_minari(tmp_path / "minari" / "test/pendulum/tiny-v0")
    assert torch.equal(trajectory_lengths(by_id), torch.tensor([6, 3]))
    exp_obs = torch.tensor(np.stack([r[0] for r in recorded]), dtype=torch.float32)
    exp_act = torch.tensor(np.stack([r[1] for r in recorded]), dtype=torch.float32)
    exp_rew = torch.tensor([r[2] for r in recorded], dtype=torch.float32)
    for td in (by_id, by_path):
        assert torch.allclose(_valid(td, "observation"), exp_obs)
        assert torch.allclose(_valid(td, "action"), exp_act)
        assert torch.allclose(_valid(td, ("next", "reward")).squeeze(-1), exp_rew)
        assert bool((exp_rew != 0).all())  # real values, not torchrl's all-zero Minari storage
        assert torch.allclose(td["next", "observation"][0, :5], td["observation"][0, 1:6])
        assert torch.equal(_valid(td, ("next", "success")).squeeze(-1), exp_rew > -1.0)
    assert by_id["next", "terminated"][1, 2] and by_id["next", "truncated"][0, 5]
    with pytest.raises(FileNotFoundError):
        load_minari("test/pendulum/absent-v0")


@pytest.mark.parametrize("damage", ["truncated", "not_a_zip", "bad_member"])
def test_a_damaged_npz_is_named_not_a_deep_traceback(tmp_path, damage):
    """A truncated, non-zip or member-corrupted ``.npz`` gives a ValueError naming the file, from the transition
    loader and the Preference-Transformer label loader alike (numpy raises BadZipFile / EOFError / zlib.error)."""
    import zipfile

    from torchrl_ftb.data.labels import load_pt_labels

    good = save_transitions_file(make_toy_dataset(num_trajectories=3, horizon=5, seed=0), tmp_path / "good.npz")
    raw = good.read_bytes()
    bad = tmp_path / f"{damage}.npz"
    if damage == "truncated":
        bad.write_bytes(raw[: len(raw) // 2])
    elif damage == "not_a_zip":
        bad.write_bytes(b"\x93NUMPY not a zip archive at all")
    else:  # a compressed member whose bytes are garbage
        with zipfile.ZipFile(bad, "w", compression=zipfile.ZIP_DEFLATED) as z:
            z.writestr("observations.npy", raw[:200])
        data = bytearray(bad.read_bytes())
        data[60:90] = b"\xff" * 30
        bad.write_bytes(bytes(data))
    for load in (load_transitions_file, load_pt_labels):
        with pytest.raises(ValueError, match=rf"{damage}\.npz"):
            load(bad)


def test_load_minari_names_an_episode_whose_arrays_do_not_match_its_steps(tmp_path, monkeypatch):
    """An episode with T observations (not T + 1) or without steps is refused with its id, not reshaped into
    another observation size."""
    minari = pytest.importorskip("minari")

    class Episode:
        def __init__(self, steps: int, obs_rows: int):
            self.id, self.steps = 7, steps
            self.observations = np.zeros((obs_rows, 11), np.float32)
            self.actions = np.zeros((steps, 3), np.float32)
            self.rewards = np.zeros(steps)
            self.terminations = self.truncations = np.zeros(steps, bool)
            self.infos = {}

        def __len__(self) -> int:
            return self.steps

    data = tmp_path / "fake" / "data"
    data.mkdir(parents=True)
    (data / "metadata.json").write_text("{}")
    for steps, rows in ((10, 10), (0, 1)):
        monkeypatch.setattr(minari, "MinariDataset", lambda path, s=steps, r=rows: type(
            "D", (), {"iterate_episodes": lambda self: iter([Episode(s, r)])})())
        with pytest.raises(ValueError, match=rf"episode 7 has {rows} observations for {steps} steps"):
            load_minari(tmp_path / "fake")
