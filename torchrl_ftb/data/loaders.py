"""Loaders: external offline datasets into padded trajectory batches ``[N, H]`` + ``"mask"``.

Every loader returns the trajectory batch of ``docs/conventions.md`` (``observation``,
``action``, ``("next", {observation, reward, done, terminated, truncated})``, optional
``("next", "success")`` and ``"state"``, ``"mask"``), checked with
:func:`~torchrl_ftb.data.trajectories.validate_trajectories`. Episodes end where
``terminated | truncated``; a dataset whose last transition closes no episode keeps that
tail as a trajectory whose last step is marked ``truncated`` (the data were cut).

Sources:

* **Own transition files** (:func:`load_transitions_file` / :func:`save_transitions_file`):
  ``.npz`` or HDF5 (``.h5``/``.hdf5``) with D4RL's field names, one row per transition,
  episodes stored back to back:

  ===================== =============== ======================================================
  field                 shape           meaning
  ===================== =============== ======================================================
  ``observations``      ``[T, obs]``    s_t (float)
  ``actions``           ``[T, act]``    a_t (float)
  ``rewards``           ``[T]``         r(s_t, a_t) (float; optional: reward-free data)
  ``terminals``         ``[T]``         episode ended by a true termination (bool or 0/1)
  ``timeouts``          ``[T]``         episode ended by a time limit / stop rule / data cut
  ``next_observations`` ``[T, obs]``    s_{t+1} (optional, see below)
  ``success``           ``[T]``         Meta-World success flag after the step (optional)
  ``states``            ``[T, state]``  simulator state qpos‖qvel at s_t (optional)
  ===================== =============== ======================================================

  ``[T, 1]`` is accepted wherever ``[T]`` is. Other fields (and HDF5 groups such as
  D4RL's ``infos/`` and ``metadata/``) are ignored. Without ``next_observations``, the
  next observation is taken from the following row inside an episode and set to zero on
  the last step of each episode (unknown there) — the same convention as torchrl's D4RL
  loader.
* **D4RL** HDF5 files (:func:`load_d4rl_hdf5`): the same reader (D4RL's own layout is the
  one above, ``rewards``/``terminals``/``timeouts`` required).
* **D4RL via torchrl** (:func:`load_d4rl`): the memmap folder ``<root>/<dataset_id>`` that
  :class:`torchrl.data.datasets.D4RLExperienceReplay` writes and reads (no network and no
  ``d4rl`` package needed with ``download=False``). torchrl drops the file's last transition
  and zeroes ``("next", "observation")`` on every ``done`` step; both are kept as torchrl
  stores them.
* **Minari** (:func:`load_minari`): read with the ``minari`` package itself (optional extra
  ``pip install torchrl_ftb[minari]``). torchrl 0.14.1's ``MinariExperienceReplay`` stores
  all-zero data, so it is not used.

Example:
    >>> import tempfile, os
    >>> from torchrl_ftb.data.loaders import load_transitions_file, save_transitions_file
    >>> from torchrl_ftb.testing import make_toy_dataset
    >>> trajs = make_toy_dataset(num_trajectories=4, horizon=8, seed=0)
    >>> path = save_transitions_file(trajs, os.path.join(tempfile.mkdtemp(), "toy.npz"))
    >>> back = load_transitions_file(path, obs_dim=3)
    >>> bool((back["mask"].sum(-1) == trajs["mask"].sum(-1)).all())
    True
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_ftb.data.trajectories import (
    NPZ_READ_ERRORS,
    atomic_file,
    flat_to_trajectories,
    trajectories_to_flat,
    validate_trajectories,
)

__all__ = [
    "TRANSITION_FIELDS",
    "transitions_from_arrays",
    "load_transitions_file",
    "save_transitions_file",
    "load_d4rl_hdf5",
    "load_d4rl",
    "load_minari",
]

#: Field names of the transition-file format (D4RL's names plus ``success`` and ``states``).
TRANSITION_FIELDS: tuple = (
    "observations",
    "actions",
    "rewards",
    "terminals",
    "timeouts",
    "next_observations",
    "success",
    "states",
)
_HDF5_SUFFIXES = (".h5", ".hdf5")


# --------------------------------------------------------------------------- arrays -> batch
def _as_numpy(value, *, name: str, field: str) -> np.ndarray:
    try:
        return np.asarray(value)
    except Exception as err:  # pragma: no cover - exotic array-likes only
        raise ValueError(f"{name}: field {field!r} cannot be read as an array ({err})") from err


def _check_flag(arr: np.ndarray, *, name: str, field: str, rows: int) -> np.ndarray:
    arr = _check_vector(arr, name=name, field=field, rows=rows)
    if arr.dtype != np.bool_:
        if not np.isin(arr, (0, 1)).all():
            bad = np.unique(arr[~np.isin(arr, (0, 1))])[:5]
            raise ValueError(
                f"{name}: field {field!r} must be boolean (0/1), found values {bad.tolist()}"
            )
        arr = arr.astype(bool)
    return arr


def _check_vector(arr: np.ndarray, *, name: str, field: str, rows: int) -> np.ndarray:
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1 or arr.shape[0] != rows:
        raise ValueError(
            f"{name}: field {field!r} must have shape [{rows}] (one value per transition, "
            f"like 'observations' {rows} rows), got {list(arr.shape)}"
        )
    return arr


def _check_matrix(arr: np.ndarray, *, name: str, field: str, rows: int | None) -> np.ndarray:
    if arr.ndim != 2:
        raise ValueError(f"{name}: field {field!r} must have shape [T, D], got {list(arr.shape)}")
    if rows is not None and arr.shape[0] != rows:
        raise ValueError(
            f"{name}: field {field!r} has {arr.shape[0]} rows but 'observations' has {rows} "
            f"(shapes {list(arr.shape)} vs [{rows}, ...])"
        )
    return arr


def _check_finite(arr: np.ndarray, *, name: str, field: str) -> None:
    if arr.dtype.kind in "fc":
        bad = ~np.isfinite(arr)
        if bad.any():
            first = int(np.argwhere(bad)[0][0])
            raise ValueError(
                f"{name}: field {field!r} has {int(bad.sum())} NaN/inf values "
                f"(first in row {first})"
            )


def transitions_from_arrays(
    fields: Mapping[str, np.ndarray | torch.Tensor],
    *,
    name: str = "transitions",
    obs_dim: int | None = None,
    action_dim: int | None = None,
    require_rewards: bool = False,
) -> TensorDict:
    """Turn flat transition arrays (the field names of the module docstring) into trajectories.

    Args:
        fields: mapping with ``observations``, ``actions``, ``terminals``, ``timeouts`` and
            optionally ``rewards``, ``next_observations``, ``success``, ``states``.
        name: how errors name the source (e.g. the file path).
        obs_dim: expected observation size, checked if given.
        action_dim: expected action size, checked if given.
        require_rewards: raise if ``rewards`` is missing (D4RL files always have it).

    Returns:
        The ``[N, H]`` trajectory batch, ``H`` the longest episode.

    Raises:
        ValueError: missing field, inconsistent shapes, non-boolean flags, NaN/inf values,
            or an observation/action size different from ``obs_dim``/``action_dim``.

    Example:
        >>> import numpy as np
        >>> td = transitions_from_arrays({
        ...     "observations": np.zeros((5, 2)), "actions": np.ones((5, 1)),
        ...     "rewards": np.arange(5.0), "terminals": [0, 1, 0, 0, 0],
        ...     "timeouts": [0, 0, 0, 0, 1]})
        >>> td.batch_size, td["mask"].sum(-1).tolist()
        (torch.Size([2, 3]), [2, 3])
    """
    required = ["observations", "actions", "terminals", "timeouts"] + (
        ["rewards"] if require_rewards else []
    )
    missing = [f for f in required if f not in fields]
    if missing:
        raise ValueError(f"{name}: missing required field(s) {missing} (has {sorted(fields)})")
    arrays = {k: _as_numpy(fields[k], name=name, field=k) for k in TRANSITION_FIELDS if k in fields}
    obs = _check_matrix(arrays["observations"], name=name, field="observations", rows=None)
    rows = obs.shape[0]
    if rows == 0:
        raise ValueError(f"{name}: field 'observations' has no rows (empty dataset)")
    act = _check_matrix(arrays["actions"], name=name, field="actions", rows=rows)
    terminals = _check_flag(arrays["terminals"], name=name, field="terminals", rows=rows)
    timeouts = _check_flag(arrays["timeouts"], name=name, field="timeouts", rows=rows)
    for field, arr in arrays.items():
        _check_finite(arr, name=name, field=field)
    if obs_dim is not None and obs.shape[1] != obs_dim:
        raise ValueError(
            f"{name}: field 'observations' has dimension {obs.shape[1]} but obs_dim={obs_dim} "
            "was expected "
            "(does the dataset match the environment?)"
        )
    if action_dim is not None and act.shape[1] != action_dim:
        raise ValueError(
            f"{name}: field 'actions' has dimension {act.shape[1]} but "
            f"action_dim={action_dim} was expected"
        )
    done = terminals | timeouts
    if not done[-1]:  # the data were cut mid-episode: keep the tail as a truncated episode
        timeouts = timeouts.copy()
        timeouts[-1] = True
        done = terminals | timeouts
    if "next_observations" in arrays:
        next_obs = _check_matrix(
            arrays["next_observations"], name=name, field="next_observations", rows=rows
        )
        if next_obs.shape != obs.shape:
            raise ValueError(
                f"{name}: field 'next_observations' has shape {list(next_obs.shape)} but "
                f"'observations' has {list(obs.shape)}"
            )
    else:  # following row inside an episode, zero where the episode ends (unknown)
        next_obs = np.zeros_like(obs)
        next_obs[:-1] = obs[1:]
        next_obs[done] = 0

    def f32(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)

    def flag(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.bool).unsqueeze(-1)

    nxt = {
        "observation": f32(next_obs),
        "done": flag(done),
        "terminated": flag(terminals),
        "truncated": flag(timeouts & ~terminals),
    }
    if "rewards" in arrays:
        nxt["reward"] = f32(
            _check_vector(arrays["rewards"], name=name, field="rewards", rows=rows)
        ).unsqueeze(-1)
    if "success" in arrays:
        nxt["success"] = flag(_check_flag(arrays["success"], name=name, field="success", rows=rows))
    flat = {"observation": f32(obs), "action": f32(act), "next": nxt}
    if "states" in arrays:
        flat["state"] = f32(_check_matrix(arrays["states"], name=name, field="states", rows=rows))
    trajs = flat_to_trajectories(TensorDict(flat, batch_size=[rows]), done_key="done")
    return validate_trajectories(trajs, name=name, obs_dim=obs_dim, action_dim=action_dim)


# --------------------------------------------------------------------------- own files
def _read_fields(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        except NPZ_READ_ERRORS as err:
            raise ValueError(f"{path}: not a readable npz file ({type(err).__name__}: {err})") from err
    if path.suffix in _HDF5_SUFFIXES:
        import h5py

        try:
            with h5py.File(path, "r") as f:
                # top-level datasets only: D4RL's infos/ and metadata/ groups are not transitions
                return {k: f[k][()] for k in f.keys() if isinstance(f[k], h5py.Dataset)}
        except OSError as err:
            raise ValueError(f"{path}: not a readable HDF5 file ({err})") from err
    raise ValueError(f"{path}: unknown file type {path.suffix!r} (expected .npz, .h5 or .hdf5)")


def load_transitions_file(
    path: str | os.PathLike,
    *,
    obs_dim: int | None = None,
    action_dim: int | None = None,
) -> TensorDict:
    """Load an own-format transition file (``.npz`` or ``.h5``/``.hdf5``) as trajectories.

    Args:
        path: the file (format in the module docstring).
        obs_dim: expected observation size (e.g. the env's), checked if given.
        action_dim: expected action size, checked if given.

    Returns:
        ``[N, H]`` trajectory batch.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: unknown suffix, unreadable file, or bad content (names file and field).

    Example:
        >>> import numpy as np, tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "d.npz")
        >>> np.savez(path, observations=np.zeros((4, 3)), actions=np.zeros((4, 2)),
        ...          rewards=np.ones(4), terminals=np.zeros(4), timeouts=[0, 1, 0, 1])
        >>> load_transitions_file(path)["mask"].sum(-1).tolist()
        [2, 2]
    """
    path = Path(path)
    return transitions_from_arrays(
        _read_fields(path), name=str(path), obs_dim=obs_dim, action_dim=action_dim
    )


def save_transitions_file(td: TensorDictBase, path: str | os.PathLike) -> Path:
    """Write a trajectory batch as an own-format transition file, atomically (loader's inverse).

    Valid steps are written trajectory after trajectory. ``terminals`` comes from
    ``("next", "terminated")``; ``timeouts`` marks ``("next", "truncated")`` and also the last
    step of every trajectory that ends without a flag (so episode boundaries survive the
    round trip). Keys outside the format (e.g. ``"quality"``) are not written.

    Args:
        td: ``[N, H]`` trajectory batch (validated first).
        path: target ``.npz``, ``.h5`` or ``.hdf5`` file (replaced if it exists).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Example:
        >>> import tempfile, os
        >>> from torchrl_ftb.testing import make_toy_dataset
        >>> p = save_transitions_file(make_toy_dataset(num_trajectories=2, horizon=4),
        ...                           os.path.join(tempfile.mkdtemp(), "toy.h5"))
        >>> p.suffix
        '.h5'
    """
    path = Path(path)
    if path.suffix != ".npz" and path.suffix not in _HDF5_SUFFIXES:
        raise ValueError(f"{path}: unknown file type {path.suffix!r} (expected .npz, .h5 or .hdf5)")
    validate_trajectories(td, name=str(path))
    flat = trajectories_to_flat(td)
    rows = flat.batch_size[0]
    keys = set(flat.keys(include_nested=True, leaves_only=True))

    def flag(key) -> np.ndarray:
        if key in keys:
            return flat.get(key).reshape(rows).cpu().numpy().astype(bool)
        return np.zeros(rows, dtype=bool)

    terminals = flag(("next", "terminated"))
    ends = np.zeros(rows, dtype=bool)
    ends[np.cumsum(td.get("mask").sum(-1).cpu().numpy()) - 1] = True
    timeouts = (flag(("next", "truncated")) | ends) & ~terminals
    out = {
        "observations": flat.get("observation").cpu().numpy(),
        "actions": flat.get("action").cpu().numpy(),
        "terminals": terminals,
        "timeouts": timeouts,
    }
    if ("next", "reward") in keys:
        out["rewards"] = flat.get(("next", "reward")).reshape(rows).cpu().numpy()
    if ("next", "observation") in keys:
        out["next_observations"] = flat.get(("next", "observation")).cpu().numpy()
    if ("next", "success") in keys:
        out["success"] = flag(("next", "success"))
    if "state" in keys:
        out["states"] = flat.get("state").cpu().numpy()
    with atomic_file(path) as tmp:
        if path.suffix == ".npz":
            with open(tmp, "wb") as f:  # a file object: np.savez must not append ".npz"
                np.savez(f, **out)
        else:
            import h5py

            with h5py.File(tmp, "w") as f:
                for k, v in out.items():
                    f.create_dataset(k, data=v)
    return path


# --------------------------------------------------------------------------- D4RL
def load_d4rl_hdf5(
    path: str | os.PathLike,
    *,
    obs_dim: int | None = None,
    action_dim: int | None = None,
) -> TensorDict:
    """Load a D4RL HDF5 file (e.g. ``hopper_medium_replay-v2.hdf5``) with h5py.

    Reads the top-level datasets ``observations``, ``actions``, ``rewards``, ``terminals``,
    ``timeouts`` (all required) and ``next_observations`` (used when present); D4RL's
    ``infos/`` and ``metadata/`` groups are ignored. Episodes end at ``terminals | timeouts``.

    Args:
        path: the ``.hdf5``/``.h5`` file.
        obs_dim: expected observation size, checked if given.
        action_dim: expected action size, checked if given.

    Returns:
        ``[N, H]`` trajectory batch with the true ``("next", "reward")``.

    Example:
        >>> import h5py, numpy as np, tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "d4rl.hdf5")
        >>> with h5py.File(path, "w") as f:
        ...     for k, v in dict(observations=np.zeros((3, 2)), actions=np.zeros((3, 1)),
        ...                      rewards=np.ones(3), terminals=np.array([0, 0, 1], bool),
        ...                      timeouts=np.zeros(3, bool)).items():
        ...         _ = f.create_dataset(k, data=v)
        >>> load_d4rl_hdf5(path).batch_size
        torch.Size([1, 3])
    """
    path = Path(path)
    if path.suffix not in _HDF5_SUFFIXES:
        raise ValueError(f"{path}: a D4RL file must be HDF5 (.hdf5 or .h5), got {path.suffix!r}")
    return transitions_from_arrays(
        _read_fields(path),
        name=str(path),
        obs_dim=obs_dim,
        action_dim=action_dim,
        require_rewards=True,
    )


def load_d4rl(
    dataset_id: str,
    *,
    root: str | os.PathLike,
    download: bool = False,
    obs_dim: int | None = None,
    action_dim: int | None = None,
) -> TensorDict:
    """Load a D4RL dataset through :class:`torchrl.data.datasets.D4RLExperienceReplay`.

    With ``download=False`` (default) torchrl reads the memmap folder ``<root>/<dataset_id>``
    it wrote earlier (no network, no ``d4rl`` package). The flat transitions are split into
    episodes on ``("next", "done")`` (= terminated | truncated). torchrl's root-level shifted
    ``reward``/``done`` copies and ``info`` entries are dropped; our layout keeps them under
    ``"next"``. torchrl zeroes ``("next", "observation")`` on done steps and drops the file's
    last transition; the result keeps that.

    Args:
        dataset_id: e.g. ``"hopper-medium-replay-v2"``.
        root: torchrl's D4RL root folder.
        download: let torchrl download the dataset if the folder is missing (needs network).
        obs_dim: expected observation size, checked if given.
        action_dim: expected action size, checked if given.

    Returns:
        ``[N, H]`` trajectory batch.

    Raises:
        FileNotFoundError: ``<root>/<dataset_id>`` is missing and ``download=False``.

    Example:
        >>> load_d4rl("hopper-medium-replay-v2", root="/data/d4rl")  # doctest: +SKIP
    """
    from torchrl.data.datasets import D4RLExperienceReplay

    folder = Path(root) / dataset_id
    if not download and not folder.exists():
        raise FileNotFoundError(
            f"{folder}: no torchrl D4RL memmap folder for {dataset_id!r} (pass download=True "
            "to let torchrl fetch it, or load the D4RL .hdf5 file with load_d4rl_hdf5)"
        )
    rb = D4RLExperienceReplay(dataset_id, batch_size=1, root=root, download=download)
    data = rb[:]
    if data.batch_dims == 2:  # stored with split_trajs=True: back to flat valid steps
        mask_key = "mask" if "mask" in data.keys() else ("collector", "mask")
        data = data[data.get(mask_key).bool()]
    keys = set(data.keys(include_nested=True, leaves_only=True))
    missing = [
        k
        for k in (
            "observation",
            "action",
            ("next", "observation"),
            ("next", "reward"),
            ("next", "terminated"),
        )
        if k not in keys
    ]
    if missing:
        raise ValueError(f"{folder}: not a torchrl D4RL dataset, missing key(s) {missing}")
    rows = data.batch_size[0]

    def get(key, default=None):
        return data.get(key).reshape(rows, -1).cpu().numpy() if key in keys else default

    fields = {
        "observations": get("observation"),
        "actions": get("action"),
        "rewards": get(("next", "reward")),
        "terminals": get(("next", "terminated")),
        "timeouts": get(("next", "truncated"), np.zeros(rows, dtype=bool)),
        "next_observations": get(("next", "observation")),
    }
    return transitions_from_arrays(fields, name=str(folder), obs_dim=obs_dim, action_dim=action_dim)


# --------------------------------------------------------------------------- Minari
def load_minari(
    dataset_id_or_path: str | os.PathLike,
    *,
    root: str | os.PathLike | None = None,
    obs_dim: int | None = None,
    action_dim: int | None = None,
    success_key: str = "success",
) -> TensorDict:
    """Load a local Minari dataset with the ``minari`` package (optional dependency).

    ``observations`` of a Minari episode has ``T + 1`` rows (the last one is the final next
    observation), so ``observation = observations[:-1]`` and
    ``("next", "observation") = observations[1:]``. ``infos[success_key]`` (``T + 1`` rows
    with the reset info first, or ``T``) becomes ``("next", "success")`` when present.
    Only flat ``Box`` observations and actions are supported.

    Args:
        dataset_id_or_path: a dataset folder (containing ``data/``, or the ``data`` folder itself),
            or a Minari dataset id such as ``"mujoco/hopper/medium-v0"``.
        root: datasets root for an id (default: Minari's own, ``$MINARI_DATASETS_PATH`` or
            ``~/.minari/datasets``). Nothing is downloaded.
        obs_dim: expected observation size, checked if given.
        action_dim: expected action size, checked if given.
        success_key: info entry holding the success flag.

    Returns:
        ``[N, H]`` trajectory batch.

    Raises:
        ImportError: ``minari`` is not installed.
        FileNotFoundError: no local dataset.
        ValueError: unsupported (dict/tuple) observations or bad content.

    Example:
        >>> load_minari("mujoco/hopper/medium-v0")  # doctest: +SKIP
    """
    try:
        import minari
    except ImportError as err:
        raise ImportError(
            "load_minari needs the 'minari' package: pip install 'torchrl_ftb[minari]'"
        ) from err
    candidate = Path(dataset_id_or_path)
    if candidate.is_dir():
        data_dir = candidate / "data" if (candidate / "data").is_dir() else candidate
    else:
        base = Path(root) if root is not None else Path(minari.storage.get_dataset_path(""))
        data_dir = base / str(dataset_id_or_path) / "data"
    if not (data_dir / "metadata.json").is_file():
        raise FileNotFoundError(f"{data_dir}: no local Minari dataset (missing metadata.json)")
    name = str(data_dir.parent if data_dir.name == "data" else data_dir)
    dataset = minari.MinariDataset(data_dir)
    columns: dict = {k: [] for k in TRANSITION_FIELDS if k != "states"}  # Minari keeps no sim state
    for ep in dataset.iterate_episodes():
        if not isinstance(ep.observations, np.ndarray) or not isinstance(ep.actions, np.ndarray):
            raise ValueError(
                f"{name}: episode {ep.id} has dict/tuple observations or actions; only flat Box "
                "spaces are supported"
            )
        steps = len(ep)
        for field, array, rows in (("observations", ep.observations, steps + 1), ("actions", ep.actions, steps)):
            if steps < 1 or len(array) != rows:
                raise ValueError(f"{name}: episode {ep.id} has {len(array)} {field} for {steps} steps "
                                 f"(expected {rows}; an episode needs at least one step)")
        obs = ep.observations.reshape(steps + 1, -1)
        columns["observations"].append(obs[:-1])
        columns["next_observations"].append(obs[1:])
        columns["actions"].append(ep.actions.reshape(steps, -1))
        columns["rewards"].append(np.asarray(ep.rewards).reshape(steps))
        terminals = np.asarray(ep.terminations).reshape(steps).astype(bool)
        timeouts = np.asarray(ep.truncations).reshape(steps).astype(bool)
        timeouts[-1] |= not terminals[-1]  # an episode always ends
        columns["terminals"].append(terminals)
        columns["timeouts"].append(timeouts)
        if success_key in (ep.infos or {}):
            success = np.asarray(ep.infos[success_key]).reshape(-1)
            if success.shape[0] not in (steps, steps + 1):
                raise ValueError(
                    f"{name}: episode {ep.id} info {success_key!r} has {success.shape[0]} entries "
                    f"for {steps} steps"
                )
            columns["success"].append(success[-steps:])
    if not columns["observations"]:
        raise ValueError(f"{name}: the Minari dataset has no episodes")
    if 0 < len(columns["success"]) < len(columns["observations"]):
        raise ValueError(f"{name}: info {success_key!r} is present in some episodes only")
    fields = {k: np.concatenate(v) for k, v in columns.items() if v}
    return transitions_from_arrays(
        fields, name=name, obs_dim=obs_dim, action_dim=action_dim, require_rewards=True
    )
