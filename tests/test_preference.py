"""Score model, Bradley–Terry loss, training and metrics (paper §3.2, Alg. 2, Fig. 3)."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_ftb.preference import (
    BradleyTerryLoss,
    ScoreModel,
    bradley_terry_nll,
    correlations,
    load_score_model,
    pairwise_accuracy,
    plot_preference_scatter,
    preference_metrics,
    save_score_model,
    score_trajectories,
    split_labels,
    train_score_model,
)
from torchrl_ftb.testing import make_toy_dataset

KEYS = ("observation", "action", "mask")


def toy_returns(trajs):
    return trajs["next", "reward"].squeeze(-1).sum(-1)


def scripted_labels(trajs, num_pairs, *, seed, flip=False):
    """Labels from the closed-form toy return (1 = tau1 preferred, 0.5 = tie)."""
    ret = toy_returns(trajs)
    g = torch.Generator().manual_seed(seed)
    i0 = torch.randint(0, trajs.batch_size[0], (num_pairs,), generator=g)
    i1 = torch.randint(0, trajs.batch_size[0], (num_pairs,), generator=g)
    label = (ret[i1] > ret[i0]).float()
    label[ret[i1] == ret[i0]] = 0.5
    if flip:
        label = 1.0 - label
    return TensorDict(
        {"tau0": trajs[i0].select(*KEYS), "tau1": trajs[i1].select(*KEYS), "label": label,
         "index0": i0, "index1": i1},
        batch_size=[num_pairs],
    )


@pytest.fixture(scope="module")
def toy():
    return make_toy_dataset(num_trajectories=64, horizon=32, seed=0)


@pytest.fixture(scope="module")
def trained(toy):
    torch.manual_seed(0)
    model = ScoreModel(3, 2, num_cells=32, seed=0)
    labels = scripted_labels(toy, 30, seed=1)
    out = train_score_model(model, labels, steps=60, lr=5e-3, eval_fraction=0.0, seed=0, progress=False)
    return model, out


# --------------------------------------------------------------------------- score model
def test_score_is_discounted_masked_sum_of_reward_module(toy):
    model = ScoreModel(3, 2, num_cells=16, gamma=0.9, seed=0)
    trajs = toy[:8]
    rewards = model.reward_module(trajs.select(*KEYS).clone())["next", "reward"].squeeze(-1)
    disc = 0.9 ** torch.arange(trajs.batch_size[1], dtype=torch.float32)
    expected = (rewards * disc * trajs["mask"]).sum(-1)
    out = model(trajs)
    assert out.batch_size == torch.Size([8])
    torch.testing.assert_close(out["score"], expected)
    assert float(model.gamma) == pytest.approx(0.9)


def test_padded_steps_do_not_change_the_score(toy):
    model = ScoreModel(3, 2, num_cells=16, seed=0)
    trajs = toy.select(*KEYS).clone()
    mask = trajs["mask"]
    assert not bool(mask.all()), "toy data must contain padded steps for this test"
    before = model.score(trajs)
    pad = ~mask
    trajs["observation"][pad] = 1e6
    trajs["action"][pad] = float("nan")
    after = model.score(trajs)
    torch.testing.assert_close(after, before)
    # but valid steps do matter
    trajs["observation"][mask] += 1.0
    assert not torch.allclose(model.score(trajs), before)


def test_ensemble_scores_members_mean_and_std(toy):
    model = ScoreModel(3, 2, num_cells=16, num_members=3, seed=0)
    out = model(toy[:5])
    members = out["score_members"]
    assert members.shape == (5, 3)
    assert not torch.allclose(members[:, 0], members[:, 1]), "members must be initialised independently"
    torch.testing.assert_close(out["score"], members.mean(-1))
    torch.testing.assert_close(out["score_std"], members.std(-1))
    reward = model.reward_module(toy[:5].select(*KEYS).clone())["next", "reward"]
    torch.testing.assert_close((reward.squeeze(-1) * toy[:5]["mask"]).sum(-1), out["score"])


def test_prefix_view_shares_parameters(toy):
    model = ScoreModel(3, 2, num_cells=16, seed=0)
    labels = scripted_labels(toy, 6, seed=0)
    view = model.with_prefix("tau1", score_key="score1")
    assert view.in_keys == [("tau1", "observation"), ("tau1", "action"), ("tau1", "mask")]
    view(labels)
    assert labels["score1"].shape == (6,)
    torch.testing.assert_close(labels["score1"], model.score(labels["tau1"]))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.5)
    torch.testing.assert_close(view(labels.clone())["score1"], model.score(labels["tau1"]))


def test_reward_module_relabels_flat_transitions(toy):
    model = ScoreModel(3, 2, num_cells=16, seed=0)
    flat = toy[toy["mask"]]
    out = model.reward_module(flat.exclude(("next", "reward")))
    assert out["next", "reward"].shape == (flat.batch_size[0], 1)


def test_score_trajectories_chunks_no_grad_and_checkpoint(tmp_path, toy):
    model = ScoreModel(3, 2, num_cells=16, gamma=0.95, seed=0)
    full = score_trajectories(model, toy, batch_size=1000)
    chunked = score_trajectories(model, toy, batch_size=7)
    torch.testing.assert_close(full, chunked)
    assert not full.requires_grad
    torch.save(model.state_dict(), tmp_path / "score.pt")
    other = ScoreModel(3, 2, num_cells=16, seed=123)
    other.load_state_dict(torch.load(tmp_path / "score.pt", weights_only=True))
    torch.testing.assert_close(score_trajectories(other, toy), full)
    # float64 inputs (e.g. label files) are cast to the parameter dtype
    as64 = toy.select(*KEYS).clone()
    for key in ("observation", "action"):
        as64[key] = as64[key].double()
    torch.testing.assert_close(score_trajectories(model, as64), full)


def test_observation_normalizer_makes_training_invariant_to_obs_units(tmp_path, toy):
    """With the normaliser fitted on the data, rescaling/shifting the observations (other units)
    gives the same trained model's ranking; the normaliser is saved, and a state dict written
    before it existed loads as an identity normaliser."""
    labels = scripted_labels(toy, 30, seed=1)
    shifted = toy.select(*KEYS).clone()
    shifted["observation"] = shifted["observation"] * 50.0 + 7.0
    shifted_labels = labels.clone()
    for k in ("tau0", "tau1"):
        shifted_labels[k, "observation"] = labels[k, "observation"] * 50.0 + 7.0
    scores = []
    for data, lab in ((toy, labels), (shifted, shifted_labels)):
        model = ScoreModel(3, 2, num_cells=32, seed=0).fit_normalizer(data)
        assert model.normalizer_fitted
        train_score_model(model, lab, steps=40, lr=5e-3, eval_fraction=0.0, seed=0, progress=False)
        scores.append(score_trajectories(model, data))
    torch.testing.assert_close(scores[0], scores[1], rtol=1e-3, atol=1e-3)
    torch.save(model.state_dict(), tmp_path / "score.pt")
    loaded = ScoreModel(3, 2, num_cells=32, seed=1)
    loaded.load_state_dict(torch.load(tmp_path / "score.pt", weights_only=True))
    torch.testing.assert_close(score_trajectories(loaded, shifted), scores[1])
    old = {k: v for k, v in model.state_dict().items() if "obs_" not in k}
    legacy = ScoreModel(3, 2, num_cells=32, seed=1)
    legacy.load_state_dict(old)
    assert not legacy.normalizer_fitted
    with pytest.raises(ValueError, match="NaN"):
        bad = toy.select(*KEYS).clone()
        bad["observation"][0, 0, 0] = float("nan")
        ScoreModel(3, 2, num_cells=8).fit_normalizer(bad)


def test_bad_dims_raise(toy):
    with pytest.raises(ValueError, match="observation dim"):
        ScoreModel(4, 2, num_cells=8).score(toy)
    with pytest.raises(ValueError, match="gamma"):
        ScoreModel(3, 2, gamma=1.5)


# --------------------------------------------------------------------------- BT loss
def test_bradley_terry_values_and_gradients():
    s0 = torch.tensor([0.0, 0.0, 0.0, 0.0], requires_grad=True)
    s1 = torch.tensor([0.0, 2.0, 2.0, 2.0], requires_grad=True)
    y = torch.tensor([1.0, 1.0, 0.0, 0.5])
    nll = bradley_terry_nll(s0, s1, y)
    expected = torch.tensor([math.log(2), math.log1p(math.exp(-2)), math.log1p(math.exp(2)),
                             0.5 * math.log1p(math.exp(-2)) + 0.5 * math.log1p(math.exp(2))])
    torch.testing.assert_close(nll, expected)
    nll.sum().backward()
    sig2 = 1 / (1 + math.exp(-2))
    # d/ds1 = sigmoid(s1 - s0) - y ; d/ds0 = -(that)
    torch.testing.assert_close(s1.grad, torch.tensor([-0.5, sig2 - 1, sig2, sig2 - 0.5]))
    torch.testing.assert_close(s0.grad, -s1.grad)
    # a tie at equal scores is already optimal: zero gradient
    a, b = torch.zeros(1, requires_grad=True), torch.zeros(1, requires_grad=True)
    bradley_terry_nll(a, b, torch.tensor([0.5])).sum().backward()
    assert a.grad.item() == 0.0 and b.grad.item() == 0.0


def test_bradley_terry_is_stable_for_huge_gaps():
    s0, s1 = torch.tensor([0.0, 0.0]), torch.tensor([1000.0, -1000.0])
    nll = bradley_terry_nll(s0, s1, torch.tensor([1.0, 1.0]))
    torch.testing.assert_close(nll, torch.tensor([0.0, 1000.0]))


def _constant_reward_model(bias: float) -> ScoreModel:
    """r_psi(s, a) = bias exactly, so s(tau) = bias * episode length."""
    model = ScoreModel(3, 2, num_cells=4, seed=0)
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.zero_()
        last = [p for n, p in model.named_parameters() if n.endswith("bias")][-1]
        last.fill_(bias)
    return model


def test_loss_module_on_hand_example(toy):
    model = _constant_reward_model(0.1)
    traj = toy.select(*KEYS)
    lengths = traj["mask"].sum(-1).float()
    i0, i1 = torch.tensor([0, 1, 2, 3]), torch.tensor([4, 5, 6, 7])
    label = torch.tensor([1.0, 0.0, 0.5, 1.0])
    labels = TensorDict({"tau0": traj[i0], "tau1": traj[i1], "label": label}, [4])
    out = BradleyTerryLoss(model)(labels)
    s0, s1 = 0.1 * lengths[i0], 0.1 * lengths[i1]
    torch.testing.assert_close(out["loss_preference"], bradley_terry_nll(s0, s1, label).mean())
    decided = label != 0.5
    acc = (((s1 > s0) == (label > 0.5)) & (s1 != s0))[decided].float().mean()
    torch.testing.assert_close(out["accuracy"], acc)
    assert set(out.keys()) == {"loss_preference", "accuracy", "score_gap"}


def test_loss_set_keys_and_all_tie_accuracy(toy):
    model = ScoreModel(3, 2, num_cells=8, seed=0)
    traj = toy.select(*KEYS)
    labels = TensorDict({"a": traj[:3], "b": traj[3:6], "pref": torch.full((3,), 0.5)}, [3])
    loss = BradleyTerryLoss(model)
    loss.set_keys(tau0="a", tau1="b", label="pref")
    assert ("a", "observation") in loss.in_keys and "pref" in loss.in_keys
    out = loss(labels)
    assert torch.isfinite(out["loss_preference"])
    assert math.isnan(float(out["accuracy"]))


# --------------------------------------------------------------------------- training
def test_trained_model_ranks_better_trajectories_higher(toy, trained):
    model, out = trained
    assert out["train_accuracy"] > 0.9
    pair = make_toy_dataset(num_trajectories=2, horizon=32, seed=5, quality=torch.tensor([1.0, -0.3]))
    assert toy_returns(pair)[0] > toy_returns(pair)[1]
    s = score_trajectories(model, pair)
    assert s[0] > s[1]
    metrics = preference_metrics(model, toy, true_returns=toy_returns(toy))
    assert metrics["trajectory_spearman_return"] > 0.9


def test_training_follows_the_labels_not_the_data(toy, trained):
    """Reversed labels must give a reversed ranking (the model learns from labels)."""
    model = ScoreModel(3, 2, num_cells=32, seed=0)
    train_score_model(model, scripted_labels(toy, 30, seed=1, flip=True), steps=60, lr=5e-3,
                      eval_fraction=0.0, progress=False)
    rho = correlations(score_trajectories(model, toy), toy_returns(toy))["spearman"]
    assert rho < -0.8


def test_held_out_split_logger_and_seeding(tmp_path, toy):
    from torchrl.record.loggers import CSVLogger

    labels = scripted_labels(toy, 30, seed=2)
    logger = CSVLogger(exp_name="pref", log_dir=str(tmp_path))
    kw = dict(steps=10, lr=3e-3, batch_size=8, eval_fraction=0.2, eval_interval=5, seed=3, progress=False)
    m1, m2 = ScoreModel(3, 2, num_cells=16, seed=0), ScoreModel(3, 2, num_cells=16, seed=0)
    out = train_score_model(m1, labels, logger=logger, **kw)
    assert out["num_train"] == 24 and out["num_eval"] == 6
    assert {"train_loss", "eval_loss", "eval_accuracy"} <= set(out)
    assert len(out["history"]) == 2 and all(math.isfinite(v) for h in out["history"] for v in h.values())
    logged = list(tmp_path.rglob("*.csv"))
    assert any("eval_loss" in p.name for p in logged)
    train_score_model(m2, labels, **kw)
    for p1, p2 in zip(m1.parameters(), m2.parameters()):
        torch.testing.assert_close(p1, p2)
    # explicit held-out labels
    out = train_score_model(ScoreModel(3, 2, num_cells=8, seed=0), labels, eval_labels=labels[:5],
                            steps=2, progress=False)
    assert out["num_train"] == 30 and out["num_eval"] == 5


def test_training_errors(toy):
    labels = scripted_labels(toy, 10, seed=0)
    model = ScoreModel(3, 2, num_cells=8, seed=0)
    with pytest.raises(ValueError, match="at least 2 labels"):
        train_score_model(model, labels[:1], steps=1, progress=False)
    ties = labels.clone()
    ties["label"] = torch.full((10,), 0.5)
    with pytest.raises(ValueError, match="ties"):
        train_score_model(model, ties, steps=1, eval_fraction=0.0, progress=False)
    bad = labels.clone()
    bad["tau0", "observation"][0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        train_score_model(model, bad, steps=1, progress=False)
    bad = labels.clone()
    bad["label"][0] = 2.0
    with pytest.raises(ValueError, match="label"):
        train_score_model(model, bad, steps=1, progress=False)
    broken = _constant_reward_model(float("inf"))
    with pytest.raises(FloatingPointError):
        train_score_model(broken, labels, steps=1, eval_fraction=0.0, progress=False)


def test_split_labels_warns_when_too_few(toy):
    labels = scripted_labels(toy, 3, seed=0)
    with pytest.warns(UserWarning, match="too few"):
        train, held_out = split_labels(labels, eval_fraction=0.2)
    assert held_out is None and train.batch_size == (3,)
    train, held_out = split_labels(scripted_labels(toy, 10, seed=0), eval_fraction=0.3, seed=1)
    assert train.batch_size == (7,) and held_out.batch_size == (3,)
    def rows(td):
        return sorted(zip(td["index0"].tolist(), td["index1"].tolist()))

    assert sorted(rows(train) + rows(held_out)) == rows(scripted_labels(toy, 10, seed=0))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_training_and_scoring(toy):
    model = ScoreModel(3, 2, num_cells=16, num_members=2, seed=0)
    labels = scripted_labels(toy, 20, seed=0)  # on CPU: moved by train_score_model
    train_score_model(model, labels, steps=5, lr=1e-3, eval_fraction=0.0, progress=False, device="cuda")
    assert model.gamma.device.type == "cuda"
    scores = score_trajectories(model, toy)
    assert scores.device.type == "cpu" and torch.isfinite(scores).all()
    assert preference_metrics(model, toy.to("cuda"), true_returns=toy_returns(toy))["num_trajectories"] == 64


# --------------------------------------------------------------------------- metrics
def test_preference_metrics_and_scatter(tmp_path, toy, trained):
    model, _ = trained
    held_out = scripted_labels(toy, 40, seed=9)
    success = toy["next", "success"].any(1).squeeze(-1)
    m = preference_metrics(model, toy, true_returns=toy_returns(toy), success=success, labels=held_out)
    assert m["pairwise_accuracy"] > 0.85
    assert m["trajectory_spearman_success"] > 0.3
    assert m["num_transitions"] == float(toy["mask"].sum())
    # trajectory-level agreement beats transition-level (Fig. 3's point) on this data
    assert m["trajectory_spearman_return"] > m["transition_spearman_reward"]
    png = plot_preference_scatter(model, toy, tmp_path / "fig3.png", true_returns=toy_returns(toy), title="toy")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert pairwise_accuracy(model, held_out) == pytest.approx(m["pairwise_accuracy"])
    with pytest.raises(ValueError, match="true_returns"):
        preference_metrics(model, toy, true_returns=torch.zeros(3))
    assert math.isnan(correlations(torch.ones(5), torch.arange(5.0))["spearman"])


def test_score_model_checkpoint_roundtrip_and_clear_errors(tmp_path):
    trajs = make_toy_dataset(num_trajectories=6, horizon=8, seed=0)
    model = ScoreModel(3, 2, num_cells=8, num_members=2, gamma=0.9, seed=0).fit_normalizer(trajs)
    path = save_score_model(model, tmp_path / "score.pt")
    loaded = load_score_model(path)
    assert loaded.hparams == model.hparams and loaded.normalizer_fitted
    torch.testing.assert_close(score_trajectories(loaded, trajs), score_trajectories(model, trajs))
    with pytest.raises(ValueError, match="does not fit"):
        load_score_model(path, model=ScoreModel(3, 2, num_cells=16))
    with pytest.raises(FileNotFoundError, match="no score-model checkpoint"):
        load_score_model(tmp_path / "missing.pt")
    (tmp_path / "corrupt.pt").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="corrupt"):
        load_score_model(tmp_path / "corrupt.pt")
    torch.save({"kind": "something.else"}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a torchrl_ftb.score_model"):
        load_score_model(tmp_path / "foreign.pt")


def test_ensemble_sequential_members_match_vmap_values_and_gradients():
    trajs = make_toy_dataset(num_trajectories=4, horizon=6, seed=0)
    model = ScoreModel(3, 2, num_cells=8, num_members=3, seed=0)
    step = model.reward_module.module
    td = TensorDict({"observation": trajs["observation"], "action": trajs["action"]}, trajs.batch_size)
    params = list(step.net.params_td.values(True, True))
    seq = step.members_sequential(td)
    vm = step.net(td.clone(False)).get("reward")
    torch.testing.assert_close(seq, vm)
    g_seq = torch.autograd.grad(seq.square().sum(), params)
    g_vm = torch.autograd.grad(vm.square().sum(), params)
    for a, b in zip(g_seq, g_vm):
        torch.testing.assert_close(a, b)
    # the members differ, and the CPU path is the sequential one
    assert not torch.allclose(seq[0], seq[1])
    torch.testing.assert_close(step.members(td["observation"], td["action"]), seq)


def test_sigmoid_reward_activation_is_one_definition_and_saved(tmp_path, toy):
    """``reward_activation="sigmoid"``: r_psi in (0, 1) for the score, the relabelling module and
    the saved model alike; a trained one still ranks by the labels; bad names are refused."""
    model = ScoreModel(3, 2, num_cells=16, num_members=2, reward_activation="sigmoid", seed=0)
    rewards = model.step_rewards(toy)
    assert bool((rewards > 0).all() and (rewards < 1).all())
    mask = toy["mask"]
    torch.testing.assert_close(model(toy)["score"], (rewards.mean(0) * mask).sum(-1))
    flat = toy[mask].select("observation", "action")
    torch.testing.assert_close(model.reward_module(flat)["next", "reward"].squeeze(-1), rewards.mean(0)[mask])
    # a shorter prefix of the same trajectory scores strictly lower (positive per-step reward)
    cut = toy[:1].clone()
    cut["mask"][0, 16:] = False
    assert float(model(cut)["score"][0]) < float(model(toy[:1])["score"][0])
    loaded = load_score_model(save_score_model(model, tmp_path / "s.pt"))
    assert loaded.hparams["reward_activation"] == "sigmoid"
    torch.testing.assert_close(score_trajectories(loaded, toy), score_trajectories(model, toy))
    single = ScoreModel(3, 2, num_cells=32, reward_activation="sigmoid", seed=0)
    train_score_model(single, scripted_labels(toy, 30, seed=1), steps=60, lr=5e-3, eval_fraction=0.0,
                      progress=False)
    assert correlations(score_trajectories(single, toy), toy_returns(toy))["spearman"] > 0.8
    with pytest.raises(ValueError, match="reward_activation"):
        ScoreModel(3, 2, reward_activation="relu")


def test_loading_into_a_model_with_other_numbers_is_refused(tmp_path):
    path = save_score_model(ScoreModel(3, 2, num_cells=8, reward_activation="sigmoid", seed=0), tmp_path / "s.pt")
    with pytest.raises(ValueError, match="reward_activation"):
        load_score_model(path, model=ScoreModel(3, 2, num_cells=8))
    assert load_score_model(path, model=ScoreModel(3, 2, num_cells=8, reward_activation="sigmoid")) is not None


def test_top_k_mean_picks_the_highest_scores_and_rejects_bad_k():
    from torchrl_ftb.preference import top_k_mean

    scores = torch.tensor([0.1, 0.9, 0.5, 0.7])
    success = torch.tensor([True, True, False, False])
    assert top_k_mean(scores, success, 1) == 1.0
    assert top_k_mean(scores, success, 3) == pytest.approx(1 / 3)
    assert top_k_mean(scores, success, 4) == 0.5
    with pytest.raises(ValueError, match="k=5"):
        top_k_mean(scores, success, 5)
    with pytest.raises(ValueError, match="differ"):
        top_k_mean(scores, success[:3], 2)


def test_stop_rule_horizon_fills_with_the_last_reward_unless_terminated(tmp_path, toy):
    """``horizon=``: ``sum_{h<n} gamma^h r_h + r_{n-1} sum_{h=n}^{H'-1} gamma^h`` for trajectories not
    terminated at their last step, the plain sum otherwise; full-length data scores as without it."""
    plain = ScoreModel(3, 2, num_cells=16, num_members=2, gamma=0.9, seed=0)
    filled = ScoreModel(3, 2, num_cells=16, num_members=2, gamma=0.9, horizon=40, seed=0)
    filled.load_state_dict(plain.state_dict())
    trajs = toy[:6].clone()
    steps = trajs.batch_size[1]
    lengths = torch.tensor([steps, 20, 3, 1, 0, 12])
    trajs["mask"] = torch.arange(steps).expand(6, steps) < lengths[:, None]
    terminated = torch.zeros(6, steps, dtype=torch.bool)
    terminated[5, 11] = True  # trajectory 5 ends in a terminal state: no fill
    trajs["next", "terminated"] = terminated.reshape(trajs["next", "terminated"].shape)
    with torch.no_grad():
        rewards = plain.step_rewards(trajs)  # [C, 6, H]
        expected = plain.score(trajs, members=True).clone()
        for i, n in enumerate(lengths.tolist()):
            if n and i != 5:
                expected[:, i] += rewards[:, i, n - 1] * sum(0.9**h for h in range(n, 40))
        torch.testing.assert_close(filled.score(trajs, members=True), expected)
        # the same through a prefix view (what the Bradley-Terry loss reads)
        labels = TensorDict({"tau1": trajs}, batch_size=[6])
        torch.testing.assert_close(filled.with_prefix("tau1", score_key="s")(labels)["s"], expected.mean(0))
        # no termination flag (the diffuser's samples): every trajectory is filled
        bare = trajs.select(*KEYS)
        assert float(filled.score(bare)[5]) != pytest.approx(float(expected.mean(0)[5]))
        # full-length trajectories: the paper's sum
        full = toy[:4].select(*KEYS).clone()
        full["mask"][:] = True
        same = ScoreModel(3, 2, num_cells=16, num_members=2, gamma=0.9, horizon=steps, seed=0)
        same.load_state_dict(plain.state_dict())
        torch.testing.assert_close(same.score(full), plain.score(full))
    loaded = load_score_model(save_score_model(filled, tmp_path / "h.pt"))
    assert loaded.horizon == 40
    torch.testing.assert_close(score_trajectories(loaded, trajs), score_trajectories(filled, trajs))
    with pytest.raises(ValueError, match="horizon"):
        load_score_model(tmp_path / "h.pt", model=ScoreModel(3, 2, num_cells=16, num_members=2, gamma=0.9))
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        ScoreModel(3, 2, horizon=0)


def test_the_loss_and_training_read_the_termination_flag_the_fill_reads(toy):
    """With ``horizon`` the Bradley-Terry loss scores each side as :meth:`ScoreModel.score` scores the whole
    trajectories, termination flag included (a terminated trajectory is not filled): the loss on labels equals the
    Bradley-Terry NLL of the model's scores, and ``train_score_model`` keeps the flag in what it trains on."""
    trajs = toy[:4].clone()
    steps = trajs.batch_size[1]
    trajs["mask"] = torch.arange(steps).expand(4, steps) < torch.tensor([steps, 5, 3, 9])[:, None]
    terminated = torch.zeros(4, steps, dtype=torch.bool)
    terminated[1, 4] = terminated[2, 2] = True  # two trajectories end in a terminal state: no fill
    trajs["next", "terminated"] = terminated.reshape(trajs["next", "terminated"].shape)
    model = ScoreModel(3, 2, num_cells=16, gamma=0.9, horizon=40, seed=0)
    i0, i1 = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 3])
    labels = TensorDict({"tau0": trajs[i0], "tau1": trajs[i1], "label": torch.tensor([1.0, 0.0, 1.0])}, batch_size=[3])
    loss_fn = BradleyTerryLoss(model)
    assert ("tau0", "next", "terminated") in loss_fn.in_keys
    with torch.no_grad():
        scores = model.score(trajs)
        expected = bradley_terry_nll(scores[i0], scores[i1], labels["label"]).mean()
        torch.testing.assert_close(loss_fn(labels)["loss_preference"], expected)
        # what training keeps of the labels still carries the flag (it was dropped: scored as never terminated)
        kept = labels.select(*loss_fn.in_keys, strict=False)
        torch.testing.assert_close(loss_fn(kept)["loss_preference"], expected)
        assert float(loss_fn(labels.exclude(("tau0", "next"), ("tau1", "next")))["loss_preference"]) != \
            pytest.approx(float(expected))
    train_score_model(model, labels, steps=2, eval_fraction=0.0, seed=0, progress=False)  # runs with the flag


def test_stop_rule_horizon_removes_the_length_advantage(toy):
    """With positive per-step rewards a trajectory cut short by a stop rule scores below its full
    version under the plain sum, and the same under the fill when its steps are alike."""
    model = ScoreModel(3, 2, num_cells=16, reward_activation="sigmoid", seed=0)
    filled = ScoreModel(3, 2, num_cells=16, reward_activation="sigmoid", horizon=toy.batch_size[1], seed=0)
    filled.load_state_dict(model.state_dict())
    steady = toy[:1].select(*KEYS).clone()
    steady["mask"][:] = True
    steady["observation"][:] = steady["observation"][:, :1]  # the same state and action at every step
    steady["action"][:] = steady["action"][:, :1]
    short = steady.clone()
    short["mask"][0, 10:] = False
    with torch.no_grad():
        assert float(model.score(short)[0]) < float(model.score(steady)[0])
        torch.testing.assert_close(filled.score(short), filled.score(steady))
