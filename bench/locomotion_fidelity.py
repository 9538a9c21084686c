"""Can the simulator re-run a locomotion dataset's own trajectories? The check behind the locomotion readings.

For the ``--num`` best trajectories of a dataset (by recorded return), replays each one's recorded actions
open loop and compares the return with the recorded one, three ways:

* ``from_observation``: from the state rebuilt from its first observation, as the recipe's readings do
  (:func:`torchrl_ftb.envs.replay_locomotion_actions`; a fresh ``mjData`` per episode);
* ``from_stored_state``: from the dataset's stored simulator state (float32, x included), also a fresh ``mjData``;
* ``from_observation_after_another``: as the first, but without resetting ``mjData`` after another trajectory was
  run (the readings before session 35 did so): the contact solver's warm start of that run carries over.

Hopper and Walker2d re-run their data exactly; HalfCheetah's contacts amplify any difference in the start.

Usage::

    python bench/locomotion_fidelity.py --dataset halfcheetah-medium-replay --num 5 \
        --out bench/results/locomotion_fidelity_halfcheetah.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchrl_ftb.datasets import make_dataset  # noqa: E402
from torchrl_ftb.envs import locomotion_env_id, replay_locomotion_actions  # noqa: E402
from torchrl_ftb.envs.locomotion import _run_episode, _sim, _state_from_obs  # noqa: E402
from torchrl_ftb.provenance import run_record, write_json  # noqa: E402


def _rollout(u, actions: np.ndarray) -> float:
    """Return of ``actions`` (clipped) run open loop from the simulator's current state: the library's loop."""
    return float(_run_episode(u, None, len(actions), lambda t: np.clip(actions[t], -1.0, 1.0))["reward"].sum())


def fidelity(dataset: str, num: int, *, cache_dir: str | Path | None = None) -> list[dict]:
    """Recorded vs replayed return of the ``num`` best trajectories of ``dataset`` (see the module docstring);
    ``cache_dir``: the datasets' cache (default: ``make_dataset``'s)."""
    import mujoco

    env, kind = dataset.split("-", 1)
    data, _ = make_dataset(env, kind=kind, cache_dir=cache_dir, progress=False)
    if "state" not in data.keys():
        raise ValueError(f"{dataset}: the dataset has no stored simulator state ('state')")
    recorded = data["next", "reward"].squeeze(-1).mul(data["mask"]).sum(-1)
    u = _sim(locomotion_env_id(env))
    nq = u.model.nq
    rows = []
    order = recorded.argsort(descending=True)[:num].tolist()
    for rank, i in enumerate(order):
        n = int(data["mask"][i].sum())
        obs, act = data["observation"][i], data["action"][i, :n].double().numpy()
        row = {"trajectory": i, "length": n, "recorded": float(recorded[i])}
        row["from_observation"] = float(replay_locomotion_actions(env, obs[:1], [act])[0]["reward"].sum())
        state = data["state"][i, 0].double().numpy()
        mujoco.mj_resetData(u.model, u.data)
        u.set_state(state[:nq], state[nq:])
        row["from_stored_state"] = _rollout(u, act)
        other = order[(rank + 1) % len(order)]  # another trajectory first, then no reset: the old readings
        mujoco.mj_resetData(u.model, u.data)
        _rollout(u, data["action"][other, : int(data["mask"][other].sum())].double().numpy())
        u.set_state(*_state_from_obs(u, obs[0].double().numpy()))  # no reset: the warm start carries over
        row["from_observation_after_another"] = _rollout(u, act)
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", default="halfcheetah-medium-replay", help="<env>-<kind>, e.g. hopper-medium-replay")
    parser.add_argument("--num", type=int, default=5)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    rows = fidelity(args.dataset, args.num)
    for r in rows:
        print(f"trajectory {r['trajectory']}: recorded {r['recorded']:.1f}, from its observation "
              f"{r['from_observation']:.1f}, from the stored state {r['from_stored_state']:.1f}, after another "
              f"without a reset {r['from_observation_after_another']:.1f}")
    out = Path(args.out or ROOT / "bench" / "results" / f"locomotion_fidelity_{args.dataset}.json")
    write_json(out, {**run_record(config=vars(args)), "results": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
