"""torchrl_ftb.analysis.tracking: the path tracker (goal-conditioned inverse dynamics) without the simulator."""
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_ftb.analysis import track_paths
from torchrl_ftb.policy import PathTracker, fit_path_tracker


def _mocap_like(n: int = 64, h: int = 20, seed: int = 0) -> TensorDict:
    """Trajectories whose hand moves by a[:3] / 100 per step and whose gripper opening is a[3]."""
    g = torch.Generator().manual_seed(seed)
    act = torch.rand(n, h, 4, generator=g) * 2 - 1
    obs = torch.zeros(n, h, 39)
    obs[:, 0, 4:7] = torch.rand(n, 3, generator=g)  # an object that stays put
    for t in range(1, h):
        obs[:, t] = obs[:, t - 1]
        obs[:, t, 0:3] = obs[:, t - 1, 0:3] + act[:, t - 1, 0:3] / 100
        obs[:, t, 3] = act[:, t - 1, 3]
    return TensorDict({"observation": obs, "action": act, "mask": torch.ones(n, h, dtype=torch.bool)}, [n, h])


def test_fitted_tracker_heads_for_the_next_state_of_its_path():
    """Behaviour: fitted on mocap-like transitions, the tracker's action points the hand at the target, and
    its closed-loop form follows a path step by step (then holds its last state)."""
    data = _mocap_like()
    tracker = fit_path_tracker(data, steps=600, hidden=64, seed=0)
    obs = torch.zeros(3, 39)
    target = obs.clone()
    target[0, 0], target[1, 1], target[2, 2] = 0.005, -0.005, 0.005  # half a step's reach along x, -y, z
    with torch.no_grad():
        act = tracker(obs, target)
    assert act[0, 0] > 0.2 and act[1, 1] < -0.2 and act[2, 2] > 0.2
    assert float(act.abs().max()) <= 1.0
    # closed loop on a simple "simulator" (the same mocap rule): the hand reaches the path's end
    path = torch.zeros(6, 39)
    path[:, 0] = torch.linspace(0, 0.025, 6)
    control, o = tracker.controller(path.numpy(), 6), np.zeros(39)
    for _ in range(8):
        a = control(o)
        o = o.copy()
        o[0:3] += a[:3] / 100
        o[3] = a[3]
    assert o[0] == pytest.approx(0.025, abs=0.003) and abs(o[1]) < 0.003


def test_tracker_fit_is_seeded_and_rejects_bad_input():
    data = _mocap_like(n=8, h=5)
    a, b = (fit_path_tracker(data, steps=20, hidden=16, seed=3) for _ in range(2))
    x = torch.randn(4, 39)
    assert torch.equal(a(x, x), b(x, x))
    assert not torch.equal(a(x, x), fit_path_tracker(data, steps=20, hidden=16, seed=4)(x, x))
    lone = data.clone()
    lone["mask"][:, 1:] = False
    with pytest.raises(ValueError, match="no pair of consecutive valid steps"):
        fit_path_tracker(lone, steps=1)
    with pytest.raises(ValueError, match=r"dims \(0, 40\) exceed the observation's 39"):
        fit_path_tracker(data, steps=1, dims=(0, 40))
    with pytest.raises(ValueError, match="at least one step"):
        PathTracker(39, 4, hidden=4).controller(np.zeros((3, 39)), 0)
    with pytest.raises(ValueError, match="2 jobs, 1 paths and 1 lengths"):
        track_paths("button-press-v3", [(0, 0), (0, 1)], torch.zeros(1, 3, 39), [3], a, seed=0, max_steps=3)


def test_relabel_changes_only_the_chosen_rows_valid_steps():
    data = _mocap_like(n=4, h=6)
    data["mask"][1, 4:] = False
    tracker = fit_path_tracker(data, steps=200, hidden=32, seed=0)
    out = tracker.relabel(data, torch.tensor([False, True, False, False]))
    assert torch.equal(out["action"][[0, 2, 3]], data["action"][[0, 2, 3]])
    assert torch.equal(out["action"][1, 4:], data["action"][1, 4:])  # padding kept
    assert not torch.equal(out["action"][1, :4], data["action"][1, :4])
    # the relabelled actions explain the hand's path about as well as the recorded ones (mocap rule)
    step = data["observation"][1, 1:4, 0:3] - data["observation"][1, 0:3, 0:3]
    assert float((out["action"][1, :3, :3] / 100 - step).abs().max()) < 0.004
    with pytest.raises(ValueError, match=r"rows has shape \[3\], expected \[4\]"):
        tracker.relabel(data, torch.ones(3, dtype=torch.bool))


def test_recipe_relabel_generated_is_off_by_default_and_checks_its_options(tmp_path):
    import types
    from pathlib import Path

    from omegaconf import OmegaConf

    from torchrl_ftb.testing import load_script

    recipe = load_script(Path(__file__).resolve().parents[1] / "recipes" / "ftb_offline.py", "recipe_relabel")
    data = _mocap_like(n=4, h=6)
    run = types.SimpleNamespace(path=tmp_path)
    cfg = OmegaConf.create({"seed": 0, "progress": False, "bc": {}, "tracker": {"steps": 20}})
    generated = torch.tensor([True, False, False, False])
    assert recipe.relabel_generated(cfg, run, data, generated, data) is data  # off: the diffuser's actions
    assert not (tmp_path / "checkpoints" / "tracker.pt").exists()  # and no tracker fitted
    on = OmegaConf.merge(cfg, {"bc": {"relabel_actions": True}})
    out = recipe.relabel_generated(on, run, data, generated, data)
    assert torch.equal(out["action"][1:], data["action"][1:]) and not torch.equal(out["action"][0], data["action"][0])
    assert recipe.relabel_generated(on, run, data, torch.zeros(4, dtype=torch.bool), data) is data  # nothing generated
    with pytest.raises(ValueError, match="bc.relabel_actions='yes'"):
        recipe.relabel_generated(OmegaConf.merge(cfg, {"bc": {"relabel_actions": "yes"}}), run, data, generated, data)
    with pytest.raises(ValueError, match="tracker.steps=0"):
        recipe.relabel_generated(OmegaConf.merge(on, {"tracker": {"steps": 0}}), run, data, generated, data)


def test_recipe_fits_one_tracker_per_run_and_refits_when_its_steps_change(tmp_path, monkeypatch):
    """bc.relabel_actions and analysis.tracked share one fit (checkpoints/tracker.pt, loaded with
    weights_only=True); the loaded tracker acts as the fitted one; tracker.steps changed on resume refits;
    a foreign file there is a clear error."""
    import types
    from pathlib import Path

    from omegaconf import OmegaConf

    from torchrl_ftb.testing import load_script

    recipe = load_script(Path(__file__).resolve().parents[1] / "recipes" / "ftb_offline.py", "recipe_tracker_ckpt")
    fits = []
    real_fit = recipe.fit_path_tracker
    monkeypatch.setattr(recipe, "fit_path_tracker", lambda *a, **k: fits.append(k["steps"]) or real_fit(*a, **k))
    data, run = _mocap_like(n=4, h=6), types.SimpleNamespace(path=tmp_path)
    cfg = OmegaConf.create({"seed": 0, "tracker": {"steps": 20}})
    first = recipe.path_tracker(cfg, run, data, progress=False)
    again = recipe.path_tracker(cfg, run, data, progress=False)
    assert fits == [20]
    x = torch.randn(3, 39)
    assert torch.equal(first(x, x), again(x, x))
    recipe.path_tracker(OmegaConf.merge(cfg, {"tracker": {"steps": 30}}), run, data, progress=False)
    assert fits == [20, 30]
    # redo_from keeps the tracker unless the dataset itself is redone
    for redo, kept in (("bc", True), ("dataset", False)):
        recipe.RunDir(OmegaConf.create({"run_dir": str(tmp_path), "resume": True, "overwrite": False,
                                        "redo_from": redo}))
        assert (tmp_path / "checkpoints" / "tracker.pt").exists() is kept
    recipe.path_tracker(cfg, run, data, progress=False)
    assert fits == [20, 30, 20]
    torch.save({"kind": "something else"}, tmp_path / "checkpoints" / "tracker.pt")
    with pytest.raises(ValueError, match="tracker.pt: not a torchrl_ftb.path_tracker checkpoint"):
        recipe.path_tracker(cfg, run, data, progress=False)


def test_controller_acts_as_the_module_does():
    """The closed-loop form (numpy, one call per simulator step) gives the module's own actions along a path."""
    tracker = fit_path_tracker(_mocap_like(n=8, h=5), steps=20, hidden=16, seed=0)
    path = torch.randn(4, 39, dtype=torch.float64)
    control = tracker.controller(path.numpy(), 4)
    obs = torch.randn(5, 39, dtype=torch.float64)
    got = torch.as_tensor(np.stack([control(o.numpy()) for o in obs]))
    targets = path[[1, 2, 3, 3, 3]]  # the next state, then the last one held
    with torch.no_grad():
        want = tracker.double()(obs, targets)
    torch.testing.assert_close(got, want)
