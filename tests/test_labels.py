"""Preference labels: teachers against closed-form returns, label sets, PT files, persistence."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_ftb.data.labels import (
    LOCOMOTION_NUM_LABELS,
    METAWORLD_NUM_LABELS,
    ReturnTeacher,
    SuccessTeacher,
    check_labels_match,
    load_labels,
    load_pt_labels,
    make_scripted_labels,
    make_teacher,
    save_labels,
    true_return,
)
from torchrl_ftb.testing import make_toy_dataset, toy_reward

PT_DIR = (
    Path(__file__).resolve().parents[2]
    / "shared"
    / "data"
    / "pt-human-labels"
    / "hopper-medium-expert-v2"
)


@pytest.fixture(scope="module")
def trajs():
    return make_toy_dataset(num_trajectories=24, horizon=12, seed=5)


def _manual_return(td, i, gamma=1.0):
    total = 0.0
    for h in range(td.batch_size[1]):
        if td["mask"][i, h]:
            total += gamma**h * float(toy_reward(td["observation"][i, h], td["action"][i, h]))
    return total


def test_true_return_is_masked_discounted_sum_of_closed_form_reward(trajs):
    assert not bool(trajs["mask"].all())  # some episodes terminate early: padding matters
    for gamma in (1.0, 0.9):
        ret = true_return(trajs, discount=gamma)
        expected = torch.tensor(
            [_manual_return(trajs, i, gamma) for i in range(trajs.batch_size[0])]
        )
        torch.testing.assert_close(ret, expected.float(), atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="no .*'reward'"):
        true_return(trajs.exclude(("next", "reward")))


def test_true_return_horizon_fill_only_for_stop_rule_episodes():
    # three episodes in H=4: cut at 3 (stop rule), terminated at 3, full length 4 (time limit)
    mask = torch.tensor([[1, 1, 1, 0], [1, 1, 1, 0], [1, 1, 1, 1]], dtype=torch.bool)
    reward = torch.tensor([[1.0, 1.0, 2.0, 0.0], [1.0, 1.0, 2.0, 0.0], [1.0, 1.0, 1.0, 3.0]])
    terminated = torch.zeros(3, 4, dtype=torch.bool)
    terminated[1, 2] = True
    td = TensorDict(
        {"mask": mask, "next": {"reward": reward[..., None], "terminated": terminated[..., None]}},
        [3, 4],
    )
    g = 0.9
    ret = true_return(td, discount=g, horizon=6)
    expected = torch.tensor(
        [
            1 + g + 2 * g**2 + 2 * (g**3 + g**4 + g**5),  # keeps earning its last reward to step 5
            1 + g + 2 * g**2,  # terminated: absorbing, nothing added
            1 + g + g**2 + 3 * g**3 + 3 * (g**4 + g**5),
        ]
    )
    torch.testing.assert_close(ret, expected.float())
    # stop rule (episode ends 2 steps after success): the plain sum prefers the slow success,
    # the horizon fill prefers the fast one
    fast_slow = TensorDict(
        {
            "mask": torch.tensor([[1, 1, 1, 0, 0, 0], [1, 1, 1, 1, 1, 1]], dtype=torch.bool),
            "next": {
                "reward": torch.tensor([[0.5, 1, 1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5, 1, 1]])[
                    ..., None
                ],
                "terminated": torch.zeros(2, 6, 1, dtype=torch.bool),
            },
        },
        [2, 6],
    )
    torch.testing.assert_close(true_return(fast_slow), torch.tensor([2.5, 4.0]))
    torch.testing.assert_close(true_return(fast_slow, horizon=8), torch.tensor([7.5, 6.0]))
    teacher = ReturnTeacher(horizon=8)
    # tau0 = slow, tau1 = fast: label 1 (fast) with the fill, 0 (slow) with the plain sum
    assert (
        teacher(fast_slow[1:], fast_slow[:1]).item() == 1.0
        and ReturnTeacher()(fast_slow[1:], fast_slow[:1]).item() == 0.0
    )


def test_return_teacher_agrees_with_true_returns_and_ties_give_half(trajs):
    teacher = ReturnTeacher()
    tau0, tau1 = trajs[:12], trajs[12:]
    ret = true_return(trajs)
    label = teacher(tau0, tau1)
    assert torch.equal(label, (ret[12:] > ret[:12]).float())
    assert 0 < label.sum() < 12  # both outcomes occur: the test can fail both ways
    assert torch.equal(teacher(tau1, tau0), 1 - label)
    assert bool((teacher(tau0, tau0) == 0.5).all())
    diff = (ret[12:] - ret[:12]).abs()
    sorted_diff = diff.sort().values
    tol = (
        float(sorted_diff[5] + sorted_diff[6]) / 2
    )  # half the pairs within tolerance, none on its edge
    tied = ReturnTeacher(tie_tol=tol)(tau0, tau1)
    assert torch.equal(tied == 0.5, diff <= tol) and int((tied == 0.5).sum()) == 6
    assert torch.equal(tied[diff > tol], label[diff > tol])


def test_success_teacher_prefers_success_over_higher_return(trajs):
    success = trajs["next", "success"].squeeze(-1).any(-1)
    s, f = int(success.nonzero()[0]), int((~success).nonzero()[0])
    pair0 = torch.stack([trajs[s], trajs[f]]).clone()
    pair0["next", "reward"][1] = 10.0 * pair0["mask"][1, :, None]  # the failure now earns far more
    swapped = pair0[[1, 0]]
    assert torch.equal(ReturnTeacher()(pair0[:1], pair0[1:]), torch.tensor([1.0]))
    assert torch.equal(SuccessTeacher()(pair0[:1], pair0[1:]), torch.tensor([0.0]))
    assert torch.equal(SuccessTeacher()(swapped[:1], swapped[1:]), torch.tensor([1.0]))
    # both or neither succeed: the return decides
    both = success[:12] == success[12:]
    assert both.any()
    torch.testing.assert_close(
        SuccessTeacher()(trajs[:12], trajs[12:])[both],
        ReturnTeacher()(trajs[:12], trajs[12:])[both],
    )
    with pytest.raises(ValueError, match="success"):
        SuccessTeacher()(
            trajs.exclude(("next", "success"))[:2], trajs.exclude(("next", "success"))[2:4]
        )


def test_teacher_names_registry_and_config():
    assert make_teacher("return").name == "return" and make_teacher("success").name == "success"
    assert (
        make_teacher("return", discount=0.99, horizon=500).name
        == "return(discount=0.99, horizon=500)"
    )
    assert isinstance(make_teacher("success"), SuccessTeacher)
    cfg = make_teacher("success", tie_tol=0.1).config()
    assert json.loads(json.dumps(cfg))["name"] == "success(tie_tol=0.1)"
    with pytest.raises(ValueError, match="unknown teacher 'human'"):
        make_teacher("human")
    with pytest.raises(ValueError, match="discount"):
        ReturnTeacher(discount=0.0)
    with pytest.raises(TypeError):
        ReturnTeacher(0.99)  # keyword-only
    assert (METAWORLD_NUM_LABELS, LOCOMOTION_NUM_LABELS) == (30, 15)


def test_scripted_labels_are_deterministic_distinct_and_correct(trajs):
    teacher = ReturnTeacher()
    a = make_scripted_labels(trajs, num_pairs=40, teacher=teacher, seed=3)
    b = make_scripted_labels(trajs, num_pairs=40, teacher=teacher, seed=3)
    c = make_scripted_labels(trajs, num_pairs=40, teacher=teacher, seed=4)
    assert torch.equal(a["index0"], b["index0"]) and torch.equal(a["label"], b["label"])
    assert not torch.equal(a["index0"], c["index0"])
    i0, i1 = a["index0"], a["index1"]
    assert bool((i0 != i1).all())
    pairs = {tuple(sorted(p)) for p in zip(i0.tolist(), i1.tolist(), strict=True)}
    assert len(pairs) == 40  # without replacement
    assert bool((i0 < i1).any()) and bool((i0 > i1).any())  # random orientation
    ret = true_return(trajs)
    assert torch.equal(a["label"], (ret[i1] > ret[i0]).float())
    assert torch.equal(a["tau0", "observation"], trajs["observation"][i0])
    assert a["teacher"] == "return"
    check_labels_match(a, trajs)


def test_scripted_labels_exhaust_all_pairs_then_refuse_more():
    small = make_toy_dataset(num_trajectories=6, horizon=5, seed=0)
    labels = make_scripted_labels(small, num_pairs=15, teacher=ReturnTeacher(), seed=0)
    pairs = {
        tuple(sorted(p))
        for p in zip(labels["index0"].tolist(), labels["index1"].tolist(), strict=True)
    }
    assert pairs == {(i, j) for i in range(6) for j in range(i + 1, 6)}
    with pytest.raises(ValueError, match="asked for 16 pairs but 6 trajectories have only 15"):
        make_scripted_labels(small, num_pairs=16, teacher=ReturnTeacher(), seed=0)


def test_scripted_pairs_are_uniform():
    small = make_toy_dataset(num_trajectories=5, horizon=4, seed=0)
    counts = torch.zeros(5, 5)
    for seed in range(150):
        lab = make_scripted_labels(small, num_pairs=3, teacher=ReturnTeacher(), seed=seed)
        for i, j in zip(lab["index0"].tolist(), lab["index1"].tolist(), strict=True):
            counts[min(i, j), max(i, j)] += 1
    upper = counts[torch.triu(torch.ones(5, 5, dtype=torch.bool), 1)]
    assert (
        upper.sum() == 450 and bool((upper > 20).all()) and bool((upper < 75).all())
    )  # expected 45 each


def test_segment_labels_cut_valid_windows_and_use_segment_returns(trajs):
    seg_len = 5
    labels = make_scripted_labels(
        trajs, num_pairs=30, teacher=ReturnTeacher(), seed=0, segment_length=seg_len
    )
    assert labels["tau0"].batch_size == torch.Size([30, seg_len])
    lengths = trajs["mask"].sum(-1)
    for side, idx, start in (("tau0", "index0", "start0"), ("tau1", "index1", "start1")):
        index, begin = labels[idx], labels[start]
        assert bool((begin >= 0).all()) and bool(
            (begin <= (lengths[index] - seg_len).clamp(min=0)).all()
        )
        for m in range(30):
            window = trajs[int(index[m]), int(begin[m]) : int(begin[m]) + seg_len]
            assert torch.equal(labels[side][m]["observation"], window["observation"])
            assert torch.equal(labels[side][m]["mask"], window["mask"])
    seg_ret0 = (labels["tau0", "next", "reward"].squeeze(-1) * labels["tau0", "mask"]).sum(-1)
    seg_ret1 = (labels["tau1", "next", "reward"].squeeze(-1) * labels["tau1", "mask"]).sum(-1)
    assert torch.equal(labels["label"], (seg_ret1 > seg_ret0).float())
    assert bool((labels["start0"] > 0).any())  # windows really move
    check_labels_match(labels, trajs)
    with pytest.raises(ValueError, match="segment_length"):
        make_scripted_labels(trajs, num_pairs=3, teacher=ReturnTeacher(), seed=0, segment_length=13)
    with pytest.raises(ValueError, match="horizon"):
        make_scripted_labels(
            trajs, num_pairs=3, teacher=ReturnTeacher(horizon=20), seed=0, segment_length=4
        )


def test_check_labels_match_rejects_other_datasets(trajs):
    labels = make_scripted_labels(trajs, num_pairs=10, teacher=ReturnTeacher(), seed=1)
    other = make_toy_dataset(num_trajectories=24, horizon=12, seed=6)
    with pytest.raises(ValueError, match="another dataset"):
        check_labels_match(labels, other)
    with pytest.raises(ValueError, match=r"outside \[0, 8\)"):
        check_labels_match(labels, trajs[:8])
    wide = trajs.clone()
    wide.set("observation", torch.cat([wide["observation"], torch.zeros(24, 12, 2)], -1))
    with pytest.raises(ValueError, match="obs_dim=5"):
        check_labels_match(labels, wide)


def test_save_load_labels_roundtrip(tmp_path, trajs):
    labels = make_scripted_labels(
        trajs, num_pairs=8, teacher=SuccessTeacher(discount=0.99), seed=2, segment_length=4
    )
    path = save_labels(labels, tmp_path / "labels", meta={"dataset": "toy", "seed": 2})
    back, meta = load_labels(path)
    assert back["teacher"] == "success(discount=0.99)"
    assert meta["teacher"] == ["success(discount=0.99)"] and meta["dataset"] == "toy"
    assert meta["num_pairs"] == 8 and meta["segment_length"] == 4
    for key in (
        "label",
        "index0",
        "start1",
        ("tau0", "observation"),
        ("tau1", "mask"),
        ("tau1", "next", "reward"),
    ):
        assert torch.equal(back[key], labels[key]), key
    check_labels_match(back, trajs)
    other = make_scripted_labels(trajs, num_pairs=3, teacher=ReturnTeacher(), seed=0)
    save_labels(other, path)  # atomic replace
    assert load_labels(path)[0].batch_size == torch.Size([3])
    assert not any(p.name.endswith((".tmp", ".old")) for p in tmp_path.iterdir())
    with pytest.raises(FileNotFoundError):
        load_labels(tmp_path / "absent")
    (path / "meta.json").write_text(json.dumps({"format_version": 99}))
    with pytest.raises(ValueError, match="format_version 99"):
        load_labels(path)


@pytest.mark.skipif(not PT_DIR.is_dir(), reason="shared PT label files not available")
def test_load_pt_labels_real_hopper_files_orientation():
    scripted = load_pt_labels(PT_DIR / "num100_script_train.npz", obs_dim=11, action_dim=3)
    human = load_pt_labels(PT_DIR / "num100_human_train.npz", obs_dim=11)
    assert scripted.batch_size == torch.Size([100]) and scripted["tau0"].batch_size == torch.Size(
        [100, 100]
    )
    assert scripted["teacher"] == "pt-file:num100_script_train"
    raw = np.load(PT_DIR / "num100_script_train.npz")
    assert torch.equal(
        scripted["tau1", "observation"], torch.as_tensor(raw["obs_2"], dtype=torch.float32)
    )
    assert bool(scripted["tau0", "mask"].all())
    assert set(human["label"].tolist()) == {0.0, 0.5, 1.0}
    assert load_pt_labels(PT_DIR / "num100_human_eval.npz").batch_size == torch.Size([10])

    def hopper_return(side):  # Hopper reward: 1 + forward velocity (obs[5]) - 1e-3 |a|^2
        obs, act = scripted[side, "observation"], scripted[side, "action"]
        return (1.0 + obs[..., 5] - 1e-3 * act.pow(2).sum(-1)).sum(-1)

    agree = (
        ((hopper_return("tau1") > hopper_return("tau0")).float() == scripted["label"])
        .float()
        .mean()
    )
    assert agree > 0.95  # label 1 = second (tau1) preferred


def test_load_pt_labels_errors(tmp_path):
    rng = np.random.default_rng(0)
    good = {
        "obs_1": rng.normal(size=(4, 6, 3)),
        "obs_2": rng.normal(size=(4, 6, 3)),
        "action_1": rng.normal(size=(4, 6, 2)),
        "action_2": rng.normal(size=(4, 6, 2)),
        "label": np.array([0.0, 0.5, 1.0, 1.0]),
    }

    def write(name, **changes):
        arrays = {k: v for k, v in {**good, **changes}.items() if v is not None}
        np.savez(tmp_path / name, **arrays)
        return tmp_path / name

    labels = load_pt_labels(write("ok.npz"), obs_dim=3, action_dim=2, teacher="synthetic")
    assert labels["teacher"] == "synthetic" and labels["label"].tolist() == [0.0, 0.5, 1.0, 1.0]
    with pytest.raises(ValueError, match=r"miss\.npz.*missing key.*'action_2'"):
        load_pt_labels(write("miss.npz", action_2=None))
    with pytest.raises(
        ValueError, match=r"shape\.npz.*'obs_1' has shape \[4, 6, 3\] but 'obs_2' has \[4, 5, 3\]"
    ):
        load_pt_labels(write("shape.npz", obs_2=good["obs_2"][:, :5]))
    with pytest.raises(ValueError, match=r"lab\.npz.*\{0, 0.5, 1\}.*0.7"):
        load_pt_labels(write("lab.npz", label=np.array([0.0, 0.7, 1.0, 1.0])))
    with pytest.raises(ValueError, match=r"dim\.npz.*dimension 3 but obs_dim=11"):
        load_pt_labels(write("dim.npz"), obs_dim=11)
    with pytest.raises(ValueError, match=r"count\.npz.*'label' must have shape \[4\]"):
        load_pt_labels(write("count.npz", label=np.zeros(3)))
    with pytest.raises(FileNotFoundError):
        load_pt_labels(tmp_path / "absent.npz")
