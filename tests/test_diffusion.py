"""Unit tests of the trajectory diffuser pieces (fast: tiny nets, no real training)."""
from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_ftb.diffusion import (
    DiffusionLoss,
    DiffusionProcess,
    DiffusionSampler,
    TemporalUnet,
    TrajectoryDiffuser,
    TrajectoryEncoder,
    TrajectoryNormalizer,
    load_diffuser,
    make_diffuser,
    parse_overrides,
    save_diffuser,
    train_diffuser,
)
from torchrl_ftb.preference import NORMALIZED_SCORE_KEY, make_block_pair_buffer, with_normalized_scores
from torchrl_ftb.testing import make_toy_dataset

pytestmark = pytest.mark.usefixtures("one_thread")

H = 12


@pytest.fixture(scope="module")
def data():
    return make_toy_dataset(num_trajectories=32, horizon=H, seed=0)


def _diffuser(data, **kw):
    torch.manual_seed(0)
    return make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, **kw).fit_normalizer(data)


def _same_samples(d1, d2, condition) -> bool:
    """Whether two diffusers draw the same DDIM samples of ``condition`` from the same seed."""
    out = []
    for d in (d1, d2):
        torch.manual_seed(1)
        out.append(d.generate(condition, sampler="ddim", steps=2, generator=None)["observation"])
    return torch.equal(*out)


def _pairs(data, idx0, idx1):
    return TensorDict({"condition": data[idx0], "target": data[idx1]}, batch_size=[len(idx0)])


def test_unet_odd_horizon_and_bad_attention_factor():
    net = TemporalUnet(4, hidden_dim=8, dim_mults=(1, 2, 4), cond_dim=8, num_heads=2, attention_factors=(1, 4))
    out = net(torch.randn(2, 13, 4), torch.tensor([1, 999]), torch.randn(2, 5, 8), torch.ones(2, 5, dtype=torch.bool))
    assert out.shape == (2, 13, 4) and torch.isfinite(out).all()
    with pytest.raises(ValueError, match="attention_factors"):
        TemporalUnet(4, hidden_dim=8, dim_mults=(1, 2), cond_dim=8, attention_factors=(4,))


def test_cross_attention_ignores_padded_condition_steps():
    torch.manual_seed(0)
    net = TemporalUnet(4, hidden_dim=8, dim_mults=(1, 2), cond_dim=8, num_heads=2).eval()
    x, t = torch.randn(2, 8, 4), torch.tensor([10, 500])
    cond, mask = torch.randn(2, 6, 8), torch.tensor([[True] * 4 + [False] * 2] * 2)
    cond2 = cond.clone()
    cond2[:, 4:] = 100.0
    assert torch.allclose(net(x, t, cond, mask), net(x, t, cond2, mask), atol=1e-5)
    assert not torch.allclose(net(x, t, cond, mask), net(x, t, cond2, None), atol=1e-3)


def test_normalizer_uses_valid_steps_only():
    x = torch.randn(4, 6, 3)
    mask = torch.arange(6) < torch.tensor([6, 3, 2, 5])[:, None]
    a = TrajectoryNormalizer(3).fit(x, mask)
    x2 = x.clone()
    x2[~mask] = 1e3
    b = TrajectoryNormalizer(3).fit(x2, mask)
    assert torch.allclose(a.mean, b.mean) and torch.allclose(a.std, b.std)
    assert torch.allclose(a.mean, x[mask].mean(0), atol=1e-6)
    assert "mean" in a.state_dict() and "std" in a.state_dict()


def test_loss_ignores_padding_but_not_valid_steps(data):
    d = _diffuser(data)
    d.eval()  # no dropout: the loss is a deterministic function of the RNG stream
    loss = DiffusionLoss(d)
    batch = _pairs(data, torch.arange(4), torch.arange(4, 8))
    for sub, lengths in (("condition", [3, 12, 7, 5]), ("target", [9, 4, 12, 6])):
        mask = torch.arange(H) < torch.tensor(lengths)[:, None]
        batch.set((sub, "mask"), mask)
        for k in ("observation", "action"):
            batch[sub, k][~mask] = 0.0

    def value(b):
        torch.manual_seed(123)
        return loss(b)["loss_diffusion"].item()

    base = value(batch)
    changed = batch.clone()
    for sub in ("condition", "target"):
        m = changed[sub, "mask"]
        for k in ("observation", "action"):
            v = changed[sub, k]
            v[~m] = 50.0
    assert value(changed) == pytest.approx(base, abs=1e-6)
    changed["target", "action"][:, 0] += 1.0  # a valid step: must matter
    assert abs(value(changed) - base) > 1e-4


def test_padding_loss_supervises_the_data_channels_on_padded_steps(data):
    """By default the denoiser's data output on a padded target step is free; ``padding_loss`` pulls it to the
    padding's target (the valid steps' and the validity channel's terms are the same either way)."""
    batch = _pairs(data, torch.arange(4), torch.arange(4, 8))
    mask = torch.arange(H) < torch.tensor([9, 4, 12, 6])[:, None]
    batch.set(("target", "mask"), mask)
    for k in ("observation", "action"):
        batch["target", k][~mask] = 0.0
    values = {}
    for padding_loss in (False, True):
        d = _diffuser(data, padding_loss=padding_loss).eval()
        assert d.config["padding_loss"] is padding_loss
        for shift in (0.0, 3.0):
            def hook(module, args, out, shift=shift):
                out = out.clone()
                out[..., :-1][~mask] += shift  # the data channels on padded steps only
                return out
            handle = d.backbone.register_forward_hook(hook)
            torch.manual_seed(123)
            values[padding_loss, shift] = DiffusionLoss(d)(batch)["loss_diffusion"].item()
            handle.remove()
    assert values[False, 3.0] == pytest.approx(values[False, 0.0], abs=1e-6)
    assert values[True, 3.0] > values[True, 0.0] + 1.0


def test_loss_keys_and_errors(data):
    d = _diffuser(data)
    loss = DiffusionLoss(d)
    batch = _pairs(data, torch.arange(4), torch.arange(4, 8))
    out = loss(batch)
    assert set(out.keys()) >= {"loss_diffusion", "diffusion_mse_data", "diffusion_mse_validity"}
    loss.set_keys(target="better")
    renamed = TensorDict({"condition": batch["condition"], "better": batch["target"]}, batch_size=[4])
    assert torch.isfinite(loss(renamed)["loss_diffusion"])
    with pytest.raises(ValueError, match="'better'"):
        loss(batch)
    bad = _pairs(data, torch.arange(4), torch.arange(4, 8))
    bad.set(("target", "observation"), torch.zeros(4, H, 5))
    with pytest.raises(ValueError, match="observation"):
        DiffusionLoss(d)(bad)
    unfit = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H)
    with pytest.raises(ValueError, match="fit_normalizer"):
        DiffusionLoss(unfit)(batch)


def test_ddpm_noise_std_is_correct():
    """Exact eps of N(0, 0.25) data: ancestral sampling must reproduce std 0.5 (variance-scaled noise does not)."""
    process = DiffusionProcess()
    s2 = 0.25
    abar = process.scheduler.alphas_cumprod

    def eps(x, t):
        a = abar[t].view(-1, 1, 1)
        return (1 - a).sqrt() * x / (a * s2 + 1 - a)

    for sampler, steps in (("ddpm", 200), ("ddim", 50), ("dpm++", 20)):
        x = process.sample(eps, (4000, 1, 1), sampler=sampler, steps=steps, generator=torch.Generator().manual_seed(0))
        assert abs(x.std().item() - 0.5) < 0.03, (sampler, x.std().item())


@pytest.mark.parametrize("sampler,steps", [("ddpm", 25), ("ddpm", 1000), ("ddim", 20), ("ddim", 50), ("dpm++", 10), ("dpm++", 20)])
def test_samplers_with_exact_denoiser_land_on_data(sampler, steps):
    """Bayes-optimal eps of a finite set of variable-length trajectories (model space, with the
    diffuser's x0 clipping): every sampler must return (near-)copies of data points, with their
    lengths. Guards the schedules, timestep spacing and the clip-through-eps conversion (a
    deterministic sampler doing worse than DDPM on a trained model is model error, not this)."""
    data = make_toy_dataset(num_trajectories=64, horizon=16, seed=0, noise=0.3)
    d = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=16).fit_normalizer(data)
    x_data = d.model_input(d.raw_data_from_td(data), data["mask"]).reshape(64, -1).double()
    abar = d.process.scheduler.alphas_cumprod.double()

    def eps(x, t):
        a, s = abar[t].sqrt()[:, None], (1 - abar[t]).sqrt()[:, None]
        xf = x.reshape(len(x), -1).double()
        w = torch.softmax(-((xf[:, None] - a[:, :, None] * x_data[None]) ** 2).sum(-1) / (2 * s**2), -1)
        return ((xf - a * (w @ x_data)) / s).reshape(x.shape).float()

    x = d.process.sample(eps, (32, 16, d.transition_dim), sampler=sampler, steps=steps,
                         generator=torch.Generator().manual_seed(0), x0_bounds=d.x0_bounds())
    dist = torch.cdist(x.reshape(32, -1).double(), x_data)
    assert dist.min(-1).values.max() < 0.05, (sampler, steps, dist.min(-1).values.max())
    lengths = d.detect_mask(x[..., -1]).sum(-1)
    assert torch.equal(lengths, data["mask"].sum(-1)[dist.argmin(-1)])
    assert (data["mask"].sum(-1) < 16).any()  # the check covers padded (shorter) trajectories


@pytest.mark.parametrize("sampler", ["ddpm", "ddim", "dpm++"])
def test_sample_prediction_is_the_same_model_seen_through_x0(sampler):
    """``prediction_type="sample"``: a denoiser that outputs the x0 an eps-denoiser implies must
    give the eps-process's samples (same noise), clipping included; and bad names are refused."""
    data = make_toy_dataset(num_trajectories=32, horizon=8, seed=0, noise=0.3)
    d = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=8).fit_normalizer(data)
    x_data = d.model_input(d.raw_data_from_td(data), data["mask"]).reshape(32, -1)
    abar = d.process.scheduler.alphas_cumprod

    def eps(x, t):
        a, s = abar[t].sqrt()[:, None], (1 - abar[t]).sqrt()[:, None]
        xf = x.reshape(len(x), -1)
        w = torch.softmax(-((xf[:, None] - a[:, :, None] * x_data[None]) ** 2).sum(-1) / (2 * s**2), -1)
        return ((xf - a * (w @ x_data)) / s).reshape(x.shape)

    def x0(x, t):
        a = abar[t].view(-1, 1, 1)
        return (x - (1 - a).sqrt() * eps(x, t)) / a.sqrt()

    x0_process = DiffusionProcess(prediction_type="sample")
    kw = dict(sampler=sampler, steps=10, x0_bounds=d.x0_bounds())
    want = d.process.sample(eps, (6, 8, d.transition_dim), generator=torch.Generator().manual_seed(0), **kw)
    got = x0_process.sample(x0, (6, 8, d.transition_dim), generator=torch.Generator().manual_seed(0), **kw)
    torch.testing.assert_close(got, want, atol=1e-3, rtol=1e-3)
    # v prediction: the v = sqrt(abar) eps - sqrt(1 - abar) x0 the same eps-denoiser implies
    v_process = DiffusionProcess(prediction_type="v_prediction")

    def v(x, t):
        a = abar[t].view(-1, 1, 1)
        return a.sqrt() * eps(x, t) - (1 - a).sqrt() * x0(x, t)

    got = v_process.sample(v, (6, 8, d.transition_dim), generator=torch.Generator().manual_seed(0), **kw)
    torch.testing.assert_close(got, want, atol=1e-3, rtol=1e-3)
    x, t = torch.randn(5, 8, 3), torch.tensor([0, 10, 500, 900, 999])
    assert torch.equal(x0_process.training_target(x, x + 1), x)  # regressed on the clean data
    assert torch.equal(d.process.training_target(x, x + 1), x + 1)  # regressed on the noise
    a = abar[t].view(-1, 1, 1)
    torch.testing.assert_close(v_process.training_target(x, x + 1, t), a.sqrt() * (x + 1) - (1 - a).sqrt() * x)
    with pytest.raises(ValueError, match="needs the timesteps"):
        v_process.training_target(x, x + 1)
    with pytest.raises(ValueError, match="prediction_type"):
        DiffusionProcess(prediction_type="velocity")


def _trains_and_survives_save_load(d, batch, data, tmp_path):
    """A few finite training steps; the saved diffuser loads with its prediction type and samples alike."""
    out = train_diffuser(d, lambda: batch, steps=3, lr=1e-2, progress=False)
    assert all(map(math.isfinite, out["losses"]))
    d2 = load_diffuser(save_diffuser(d, tmp_path / "d.pt"))
    assert d2.process.prediction_type == d.process.prediction_type
    module = dict(sampler="ddpm", steps=4, seed=3)
    a = DiffusionSampler(d, **module)(TensorDict({"condition": data[:4]}, batch_size=[4]))["sample"]
    b = DiffusionSampler(d2, **module)(TensorDict({"condition": data[:4]}, batch_size=[4]))["sample"]
    assert torch.equal(a["observation"], b["observation"])


def test_sample_prediction_trains_on_x0_and_survives_save_load(data, tmp_path):
    d = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, prediction_type="sample").fit_normalizer(data)
    assert d.process.prediction_type == "sample"
    batch = _pairs(data, torch.arange(8), torch.arange(8, 16))
    # a backbone that returns the clean target exactly has zero loss under x0 prediction only
    target = batch["target"]
    x0 = d.model_input(d.raw_data_from_td(target), target["mask"].bool())
    backbone = d.backbone
    backbone.forward = lambda x_t, t, *args, **kwargs: x0
    assert float(DiffusionLoss(d)(batch)["loss_diffusion"]) < 1e-10
    d_eps = _diffuser(data)
    d_eps.backbone.forward = lambda x_t, t, *args, **kwargs: x0
    assert float(DiffusionLoss(d_eps)(batch)["loss_diffusion"]) > 0.1
    del backbone.forward
    _trains_and_survives_save_load(d, batch, data, tmp_path)


def test_v_prediction_trains_on_the_velocity_and_survives_save_load(data, tmp_path):
    d = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, prediction_type="v_prediction").fit_normalizer(data)
    batch = _pairs(data, torch.arange(8), torch.arange(8, 16))
    # the loss regresses on v at each sample's own t; at t = T - 1 (abar ~ 0) v is -x0, which eps's loss is far from
    target = batch["target"]
    x0 = d.model_input(d.raw_data_from_td(target), target["mask"].bool())
    d_eps = _diffuser(data)
    for model, low in ((d, True), (d_eps, False)):
        model.process.sample_timesteps = lambda batch, device=None, generator=None: torch.full((batch,), 999)
        model.backbone.forward = lambda x_t, t, *args, **kwargs: -x0
        assert (float(DiffusionLoss(model)(batch)["loss_diffusion"]) < 1e-6) is low
        del model.process.sample_timesteps, model.backbone.forward
    _trains_and_survives_save_load(d, batch, data, tmp_path)


@pytest.mark.parametrize("sampler,steps", [("ddpm", 25), ("ddim", 20), ("dpm++", 20)])
def test_sdedit_strength_edits_its_start(sampler, steps):
    """SDEdit: with the Bayes-optimal eps of a finite trajectory set, a chain started from a
    data point noised to strength 0.3 must come back to that same point (the posterior at
    that noise level is concentrated on it), while strength 1 (pure noise) lands on arbitrary
    points; strength s runs round(s * steps) denoiser calls. Guards the truncated schedule,
    the start noising and DPM-Solver++'s step index."""
    data = make_toy_dataset(num_trajectories=64, horizon=16, seed=0, noise=0.3)
    d = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=16).fit_normalizer(data)
    x_data = d.model_input(d.raw_data_from_td(data), data["mask"])
    flat = x_data.reshape(64, -1).double()
    abar = d.process.scheduler.alphas_cumprod.double()
    calls = []

    def eps(x, t):
        calls.append(int(t[0]))
        a, s = abar[t].sqrt()[:, None], (1 - abar[t]).sqrt()[:, None]
        xf = x.reshape(len(x), -1).double()
        w = torch.softmax(-((xf[:, None] - a[:, :, None] * flat[None]) ** 2).sum(-1) / (2 * s**2), -1)
        return ((xf - a * (w @ flat)) / s).reshape(x.shape).float()

    def nearest(strength):
        calls.clear()
        x = d.process.sample(eps, (32, 16, d.transition_dim), sampler=sampler, steps=steps,
                             generator=torch.Generator().manual_seed(0), x0_bounds=d.x0_bounds(),
                             x_init=x_data[:32], strength=strength)
        return torch.cdist(x.reshape(32, -1).double(), flat).argmin(-1)

    kept = (nearest(0.3) == torch.arange(32)).float().mean()
    assert len(calls) == round(0.3 * steps) and calls == sorted(calls, reverse=True)
    assert kept == 1.0, (sampler, kept)
    from_noise = (nearest(1.0) == torch.arange(32)).float().mean()
    assert len(calls) == steps
    assert from_noise < 0.3, (sampler, from_noise)


def test_strength_one_ignores_init_and_bad_strength_raises(data):
    d = _diffuser(data)
    g = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    plain = d.generate(data[:3], sampler="ddim", steps=4, generator=g(), use_ema=False)
    same = d.generate(data[:3], sampler="ddim", steps=4, generator=g(), use_ema=False, init=data[:3], strength=1.0)
    assert torch.equal(plain["observation"], same["observation"])
    edit = d.generate(data[:3], sampler="ddim", steps=4, generator=g(), use_ema=False, init=data[:3], strength=0.5)
    assert not torch.equal(plain["observation"], edit["observation"])
    with pytest.raises(ValueError, match="strength"):
        DiffusionSampler(d, strength=0.0)
    with pytest.raises(ValueError, match="init"):
        d.generate(data[:3], sampler="ddim", steps=4, init=data[:2], strength=0.5, use_ema=False)
    with pytest.raises(ValueError, match="init"):
        d.generate(data[:3], sampler="ddim", steps=4, strength=0.5, use_ema=False)


@pytest.mark.parametrize("sampler", ["ddim", "dpm++", "ddpm"])
def test_sampler_denoiser_calls_and_batched_guidance(data, sampler):
    d = _diffuser(data)
    calls = []
    handle = d.backbone.register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
    try:
        d.generate(data[:3], sampler=sampler, steps=7, guidance=1.2, use_ema=False)
    finally:
        handle.remove()
    assert len(calls) == 7 <= 2 * 7
    assert set(calls) == {6}  # conditional + unconditional in ONE batched forward


def test_guided_eps_matches_separate_passes(data):
    d = _diffuser(data).eval()
    cond = d.condition_input(d.raw_data_from_td(data[:2]), data[:2]["mask"])
    emb, mask = d.encode_condition(cond, data[:2]["mask"])
    x, t = torch.randn(2, H, d.transition_dim), torch.tensor([5, 700])
    null_emb, null_mask = d.encoder.null(2, H)
    eps_c = d.backbone(x, t, emb, mask)
    eps_u = d.backbone(x, t, null_emb, null_mask)
    got = d.guided_eps(x, t, emb, mask, guidance=1.2)
    assert torch.allclose(got, eps_u + 1.2 * (eps_c - eps_u), atol=1e-5)


def test_detect_mask_prefix():
    v = torch.tensor([[1.0, 1.0, -0.1, 1.0, -1.0, -1.0], [-1.0, -1.0, -1.0, -1.0, -1.0, -1.0]])
    mask = TrajectoryDiffuser.detect_mask(v)
    assert mask.sum(-1).tolist() == [4, 1]


def test_generate_unconditional_with_reward(data):
    d = _diffuser(data, unconditional=True, reward_channel=True)
    d.update_ema()
    out = DiffusionSampler(d, sampler="ddim", steps=3, seed=0, num_samples=5)(TensorDict({}, batch_size=[]))
    s = out["sample"]
    assert s.batch_size == (5, H) and s["next", "reward"].shape == (5, H, 1)
    assert (s["observation"][~s["mask"]] == 0).all()
    with pytest.raises(ValueError, match="reward"):
        _diffuser(data, reward_channel=True).fit_normalizer(data.exclude(("next", "reward")))


def test_save_load_identical_samples_and_errors(data, tmp_path):
    d = _diffuser(data)
    batch = _pairs(data, torch.arange(8), torch.arange(8, 16))
    train_diffuser(d, lambda: batch, steps=3, lr=1e-2, progress=False)
    path = save_diffuser(d, tmp_path / "d.pt")
    d2 = load_diffuser(path)
    module = dict(sampler="dpm++", steps=4, seed=7)
    a = DiffusionSampler(d, **module)(TensorDict({"condition": data[:4]}, batch_size=[4]))["sample"]
    b = DiffusionSampler(d2, **module)(TensorDict({"condition": data[:4]}, batch_size=[4]))["sample"]
    assert torch.equal(a["observation"], b["observation"]) and torch.equal(a["mask"], b["mask"])
    c = DiffusionSampler(d2, **module)(TensorDict({"condition": data[:4]}, batch_size=[4]))["sample"]
    assert torch.equal(b["action"], c["action"])  # seed: reproducible across calls
    with pytest.raises(FileNotFoundError):
        load_diffuser(tmp_path / "missing.pt")
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="bad.pt"):
        load_diffuser(tmp_path / "bad.pt")
    other = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, hidden_dim=8)
    with pytest.raises(ValueError, match="does not match"):
        load_diffuser(path, diffuser=other)


def test_resume_continues_exactly(data, tmp_path):
    def sampler():  # draws from torch's global RNG, like torchrl's RandomSampler
        i = torch.randint(0, 32, (8,))
        return _pairs(data, i, torch.randint(0, 32, (8,)))

    a = _diffuser(data)
    train_diffuser(a, sampler, steps=4, lr=1e-3, progress=False, seed=3)
    b = _diffuser(data)
    train_diffuser(b, sampler, steps=2, lr=1e-3, progress=False, seed=3, checkpoint_dir=tmp_path)
    b2 = _diffuser(data)
    out = train_diffuser(b2, sampler, steps=4, lr=1e-3, progress=False, seed=99, checkpoint_dir=tmp_path, resume=True)
    assert out["resumed_from"] == 2 and out["step"] == 4
    sa, sb = a.state_dict(), b2.state_dict()
    assert all(torch.allclose(sa[k].float(), sb[k].float(), atol=1e-6) for k in sa)
    loaded = load_diffuser(tmp_path / "diffuser_last.pt")
    assert torch.equal(loaded.state_dict()["ema.n_averaged"], sb["ema.n_averaged"])


def test_resume_continues_the_pair_buffers_own_stream(data, tmp_path):
    """The recipe's pair buffer samples from its own seeded generator, not torch's global RNG: a resumed run
    (a fresh buffer with the same seed, as after a kill) must go on with the pairs an uninterrupted run draws."""
    from torchrl_ftb.preference import make_block_pair_buffer

    def buffer():
        return make_block_pair_buffer(data, torch.arange(32) // 8, batch_size=4, seed=5)

    a = _diffuser(data)
    train_diffuser(a, buffer(), steps=6, lr=1e-3, progress=False, seed=3)
    b = _diffuser(data)
    train_diffuser(b, buffer(), steps=3, lr=1e-3, progress=False, seed=3, checkpoint_dir=tmp_path)
    b2 = _diffuser(data)
    out = train_diffuser(b2, buffer(), steps=6, lr=1e-3, progress=False, seed=3, checkpoint_dir=tmp_path, resume=True)
    assert out["resumed_from"] == 3
    sa, sb = a.state_dict(), b2.state_dict()
    assert all(torch.allclose(sa[k].float(), sb[k].float(), atol=1e-6) for k in sa)


def test_trains_on_preference_block_pair_buffer(data):
    """The loss consumes the preference stage's replay buffer batches as they are."""
    from torchrl_ftb.preference import make_block_pair_buffer

    d = _diffuser(data)
    rb = make_block_pair_buffer(data, torch.arange(32) // 8, batch_size=6, seed=0)
    out = train_diffuser(d, rb, steps=2, lr=1e-3, progress=False, autocast_bf16=True)
    assert out["step"] == 2 and all(torch.isfinite(torch.tensor(out["losses"])))
    sample = d.generate(data[:2], sampler="ddim", steps=2, autocast_bf16=True)
    assert torch.isfinite(sample["observation"]).all()


def test_bottleneck_width_warns():
    """Fewer channels on the full-resolution path than diffused dims caps the eps-MSE; say so
    at construction (39 obs + 4 act + validity = 44 dims)."""
    import warnings

    with pytest.warns(UserWarning, match="bottleneck"):
        make_diffuser("cpu", obs_dim=39, action_dim=4, horizon=16, hidden_dim=16)
    with pytest.warns(UserWarning, match="bottleneck"):
        make_diffuser("cpu", obs_dim=39, action_dim=4, horizon=16, hidden_dim=32, cond_dim=32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_diffuser("cpu", obs_dim=39, action_dim=4, horizon=16, hidden_dim=44, cond_dim=32, dim_mults=[1, 2])
        # 30 static dims leave 14 diffused: 32 channels suffice
        make_diffuser("cpu", obs_dim=39, action_dim=4, horizon=16, hidden_dim=32, cond_dim=32,
                      static_dims=range(30))


def test_level0_skip_is_used():
    """The output at step h depends on x_t at step h through the full-resolution skip: a U-Net
    without it (Janner et al.'s) passes x_t only through a stride-2 down-sampling."""
    torch.manual_seed(0)
    net = TemporalUnet(4, hidden_dim=8, dim_mults=(1, 2, 4)).eval()
    assert len(net.ups) == len(net.downs)
    x = torch.randn(1, 16, 4, requires_grad=True)
    out = net(x, torch.tensor([5]))
    (grad,) = torch.autograd.grad(out[0, 7].sum(), x)
    assert grad[0, 7].abs().sum() > 0


def _with_constant_dims(data):
    obs = data["observation"]
    const = torch.stack([torch.full_like(obs[..., 0], 0.7), torch.zeros_like(obs[..., 0])], -1)
    out = data.clone()
    out.set("observation", torch.cat([obs, const], -1) * data["mask"][..., None])
    return out


def test_static_dims_are_not_diffused_and_restored(data, tmp_path):
    data5 = _with_constant_dims(data)
    torch.manual_seed(0)
    d = make_diffuser("tiny", obs_dim=5, action_dim=2, horizon=H, data=data5)
    assert d.static_dims == (3, 4) and d.transition_dim == 3 + 2 + 1 and d.normalizer.is_fitted
    batch = _pairs(data5, torch.arange(8), torch.arange(8, 16))
    assert torch.isfinite(DiffusionLoss(d)(batch)["loss_diffusion"])
    train_diffuser(d, lambda: batch, steps=2, lr=1e-2, progress=False)
    sample = d.generate(data5[:4], sampler="ddpm", steps=3)
    m = sample["mask"]
    assert torch.allclose(sample["observation"][..., 3][m], torch.tensor(0.7))
    assert (sample["observation"][..., 4][m] == 0).all()
    # actions are clipped to the data's range (no margin), observations may go beyond it
    act = data5["action"][data5["mask"]]
    assert (sample["action"][m] >= act.min(0).values - 1e-4).all()
    assert (sample["action"][m] <= act.max(0).values + 1e-4).all()
    # the static dims travel with the checkpoint
    d2 = load_diffuser(save_diffuser(d, tmp_path / "static.pt"))
    assert d2.static_dims == (3, 4)
    assert _same_samples(d, d2, data5[:2])
    # refitting on data where a static dim varies is an error, not silent garbage
    varying = data5.clone()
    varying["observation"][..., 3] = torch.randn_like(varying["observation"][..., 3])
    with pytest.raises(ValueError, match=r"dims \[3\].*vary"):
        d.fit_normalizer(varying)


def _load_without_option(data, tmp_path, option: str):
    """Save a default diffuser, drop ``option`` from its checkpoint's config (a checkpoint
    written before the option existed) and load it back."""
    path = save_diffuser(_diffuser(data), tmp_path / "legacy.pt")
    ckpt = torch.load(path, weights_only=True)
    ckpt["config"].pop(option)
    torch.save(ckpt, path)
    return load_diffuser(path)


def test_global_condition_path_pools_valid_steps_and_loads_legacy(data, tmp_path):
    torch.manual_seed(0)
    net = TemporalUnet(4, hidden_dim=8, dim_mults=(1, 2), cond_dim=8, num_heads=2, global_condition=True).eval()
    x, t = torch.randn(2, 8, 4), torch.tensor([10, 500])
    cond, mask = torch.randn(2, 6, 8), torch.tensor([[True] * 4 + [False] * 2] * 2)
    cond2 = cond.clone()
    cond2[:, 4:] = 100.0  # padded steps: neither attention nor the pooled path sees them
    assert torch.allclose(net(x, t, cond, mask), net(x, t, cond2, mask), atol=1e-5)
    # the pooled path alone carries the condition: with every attention block bypassed it still matters
    _bypass_attention(net)
    assert not torch.allclose(net(x, t, cond, mask), net(x, t, cond + 1.0, mask), atol=1e-4)
    plain = _bypass_attention(TemporalUnet(4, hidden_dim=8, dim_mults=(1, 2), cond_dim=8, num_heads=2).eval())
    assert torch.allclose(plain(x, t, cond, mask), plain(x, t, cond + 1.0, mask))
    # make_diffuser records the option; a checkpoint from before it existed loads without it
    diff = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, global_condition=True).fit_normalizer(data)
    assert diff.config["global_condition"] is True and diff.backbone.global_condition
    assert not getattr(_load_without_option(data, tmp_path, "global_condition").backbone, "global_condition")


def test_concat_condition_path_is_local_masked_and_loads_legacy(data, tmp_path):
    torch.manual_seed(0)
    net = TemporalUnet(4, hidden_dim=8, dim_mults=(1, 2), cond_dim=8, num_heads=2, concat_condition=True).eval()
    _bypass_attention(net)  # the concat path alone
    x, t = torch.randn(2, 6, 4), torch.tensor([10, 500])
    cond, mask = torch.randn(2, 6, 8), torch.tensor([[True] * 4 + [False] * 2] * 2)
    padded = cond.clone()
    padded[:, 4:] = 100.0  # padded condition steps are zeroed before they enter
    assert torch.allclose(net(x, t, cond, mask), net(x, t, padded, mask), atol=1e-5)
    assert not torch.allclose(net(x, t, cond, mask), net(x, t, cond + 1.0, mask), atol=1e-4)
    with pytest.raises(ValueError, match="horizon"):
        net(x, t, cond[:, :5], mask[:, :5])
    # through the diffuser: training, guided sampling (null condition) and the recorded option
    diff = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, concat_condition=True).fit_normalizer(data)
    assert diff.config["concat_condition"] is True and diff.backbone.concat_condition
    train_diffuser(diff, lambda: _pairs(data, torch.arange(8), torch.arange(8, 16)), steps=2, progress=False)
    assert diff.generate(data[:3], sampler="ddim", steps=3)["observation"].shape == (3, H, 3)
    assert not getattr(_load_without_option(data, tmp_path, "concat_condition").backbone, "concat_condition")



def test_encoder_skip_keeps_each_conditions_level_and_scale_and_loads_legacy(data, tmp_path):
    """The convolutional path ends in a GroupNorm over the horizon (here one channel per group): a condition and
    an affine copy of it (3 x + 2) encode alike away from the edges. The linear skip tells them apart."""
    torch.manual_seed(0)
    x, mask = torch.randn(2, 200, 1), torch.ones(2, 200, dtype=torch.bool)
    for skip, differ in ((False, False), (True, True)):
        enc = TrajectoryEncoder(1, embed_dim=8, linear_skip=skip).eval()
        gap = float((enc(x, mask)[0] - enc(3 * x + 2, mask)[0])[:, 10:-10].abs().max())
        assert (gap > 1.0 if differ else gap < 0.1), (skip, gap)
    diff = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, encoder_skip=True).fit_normalizer(data)
    assert diff.config["encoder_skip"] is True and diff.encoder.linear_skip
    train_diffuser(diff, lambda: _pairs(data, torch.arange(8), torch.arange(8, 16)), steps=2, progress=False)
    assert diff.generate(data[:3], sampler="ddim", steps=3)["observation"].shape == (3, H, 3)
    assert not _load_without_option(data, tmp_path, "encoder_skip").encoder.linear_skip


def test_score_condition_feeds_the_normalised_score_and_loads_legacy(data, tmp_path):
    torch.manual_seed(0)
    enc = TrajectoryEncoder(5, embed_dim=8, score_condition=True)
    x, mask = torch.randn(2, 6, 5), torch.ones(2, 6, dtype=torch.bool)
    a, _ = enc(x, mask, torch.tensor([0.0, 1.0]))
    b, _ = enc(x, mask, torch.tensor([0.0, 0.5]))
    assert torch.allclose(a[0], b[0]) and not torch.allclose(a[1], b[1])  # only the changed score moves
    with pytest.raises(ValueError, match="score="):
        enc(x, mask)
    with pytest.raises(ValueError, match="score="):
        TrajectoryEncoder(5, embed_dim=8)(x, mask, torch.zeros(2))
    with pytest.raises(ValueError, match=r"score must be \[2\]"):
        enc(x, mask, torch.zeros(3))
    diff = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, score_condition=True).fit_normalizer(data)
    assert diff.config["score_condition"] is True and diff.score_condition
    scored = with_normalized_scores(data, torch.arange(data.batch_size[0], dtype=torch.float32))
    loss = DiffusionLoss(diff)
    assert ("condition", NORMALIZED_SCORE_KEY) in loss.in_keys
    assert ("condition", NORMALIZED_SCORE_KEY) in DiffusionSampler(diff, steps=2).in_keys
    train_diffuser(diff, lambda: _pairs(scored, torch.arange(8), torch.arange(8, 16)), steps=2, progress=False)
    gen = dict(sampler="ddim", steps=3, generator=torch.Generator().manual_seed(0))
    lo = diff.generate(scored[:3], **gen)
    hi = scored[:3].clone()
    hi[NORMALIZED_SCORE_KEY] = torch.ones_like(hi[NORMALIZED_SCORE_KEY])
    gen["generator"] = torch.Generator().manual_seed(0)
    assert not torch.allclose(lo["observation"], diff.generate(hi, **gen)["observation"])  # same noise, new score
    with pytest.raises(ValueError, match="missing 'normalized_score'"):
        diff.generate(data[:3], sampler="ddim", steps=2)
    with pytest.raises(ValueError, match="missing 'normalized_score'"):
        loss(_pairs(data, torch.arange(4), torch.arange(4, 8)))
    bad = scored[:3].clone()
    bad[NORMALIZED_SCORE_KEY][0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        diff.generate(bad, sampler="ddim", steps=2)
    assert not _load_without_option(data, tmp_path, "score_condition").score_condition
    # the block pair buffer hands both sides their normalised score (min -> 0, max -> 1)
    rb = make_block_pair_buffer(data, torch.arange(data.batch_size[0]) % 3, batch_size=6, seed=0,
                                scores=torch.arange(data.batch_size[0], dtype=torch.float32))
    batch = rb.sample()
    idx = batch["index"]
    expected = idx.float() / (data.batch_size[0] - 1)
    assert torch.allclose(batch["condition", NORMALIZED_SCORE_KEY][:, 0], expected[:, 0])
    assert torch.allclose(batch["target", NORMALIZED_SCORE_KEY][:, 0], expected[:, 1])

class _Skip(torch.nn.Module):
    def forward(self, h, *_):
        return h


def _bypass_attention(net: TemporalUnet) -> TemporalUnet:
    """Replace every cross-attention slot of the U-Net (in place) by an identity."""
    for level in (*net.downs, *net.ups):
        level[1] = _Skip()
    net.mid[1] = _Skip()
    return net


def _with_stacked_frame_and_goal(data):
    """Toy obs [x(3)] -> [x(3), x one step back (3), goal(1) constant per trajectory] (7 dims)."""
    obs, mask = data["observation"], data["mask"]
    prev = torch.cat([obs[:, :1], obs[:, :-1]], 1)
    goal = torch.linspace(-1, 1, obs.shape[0])[:, None, None].expand(-1, obs.shape[1], 1)
    out = data.clone()
    out.set("observation", torch.cat([obs, prev, goal], -1) * mask[..., None])
    return out


def test_observation_structure_lagged_and_time_constant_dims(data, tmp_path):
    data7 = _with_stacked_frame_and_goal(data)
    layout = dict(lagged_dims=[(3, 0), (4, 1), (5, 2)], time_constant_dims=[6])
    torch.manual_seed(0)
    d = make_diffuser("tiny", obs_dim=7, action_dim=2, horizon=H, data=data7, **layout)
    # the three lagged dims are not diffused (the goal is: it varies across trajectories)
    assert d.transition_dim == 7 - 3 + 2 + 1 and d.static_dims == ()
    batch = _pairs(data7, torch.arange(8), torch.arange(8, 16))
    train_diffuser(d, lambda: batch, steps=2, lr=1e-2, progress=False)
    sample = d.generate(data7[:4], sampler="ddpm", steps=3)
    obs, m = sample["observation"], sample["mask"]
    pair = m[:, 1:] & m[:, :-1]
    # the stacked previous frame is exact, by construction, and the goal is constant in time
    assert torch.equal(obs[:, 1:, 3:6][pair], obs[:, :-1, 0:3][pair])
    assert torch.equal(obs[:, 0, 3:6], obs[:, 0, 0:3])
    goal = obs[..., 6]
    assert torch.allclose(goal[m], goal[:, :1].expand_as(goal)[m])
    # the same decoding applies to real data: it leaves a consistent trajectory unchanged
    raw = d.raw_data_from_td(data7)
    torch.testing.assert_close(d.apply_observation_structure(raw, data7["mask"]) * data7["mask"][..., None],
                               raw * data7["mask"][..., None])
    # the layout travels with the checkpoint
    d2 = load_diffuser(save_diffuser(d, tmp_path / "layout.pt"))
    assert d2.lagged_dims == d.lagged_dims and d2.time_constant_dims == (6,)
    # malformed layouts are clear errors
    with pytest.raises(ValueError, match="no target may be a source"):
        make_diffuser("tiny", obs_dim=7, action_dim=2, horizon=H, lagged_dims=[(3, 0), (0, 1)])
    with pytest.raises(ValueError, match="observation dims"):
        make_diffuser("tiny", obs_dim=7, action_dim=2, horizon=H, lagged_dims=[(7, 0)])


@pytest.mark.parametrize("sampler", ["ddpm", "ddim", "dpm++"])
def test_inpaint_start_holds_each_samples_first_observation_and_goal(data, sampler):
    """inpaint_start: a sample starts exactly where its condition starts (the whole first observation,
    stacked frame included) and keeps the condition's goal at every step; without it, it starts anywhere."""
    data7 = _with_stacked_frame_and_goal(data)
    torch.manual_seed(0)
    d = make_diffuser("tiny", obs_dim=7, action_dim=2, horizon=H, data=data7,
                      lagged_dims=[(3, 0), (4, 1), (5, 2)], time_constant_dims=[6])
    cond = data7[4:10]
    g = lambda: torch.Generator().manual_seed(1)  # noqa: E731
    free = d.generate(cond, sampler=sampler, steps=4, generator=g(), use_ema=False)
    held = d.generate(cond, sampler=sampler, steps=4, generator=g(), use_ema=False, inpaint_start=True)
    first = cond["observation"][:, 0]
    torch.testing.assert_close(held["observation"][:, 0], first, atol=1e-5, rtol=1e-5)
    assert (free["observation"][:, 0] - first).abs().amax() > 1e-2
    m = held["mask"]
    goal = held["observation"][..., 6]
    torch.testing.assert_close(goal[m], first[:, 6:7].expand_as(goal)[m], atol=1e-5, rtol=1e-5)
    assert bool(m[:, 0].all())
    # the flow's module form, and an SDEdit edit, start there too; a plain layout holds the first step only
    module = DiffusionSampler(d, sampler=sampler, steps=4, seed=0, inpaint_start=True, strength=0.5, use_ema=False)
    edits = module(TensorDict({"condition": cond}, batch_size=[6]))["sample"]
    torch.testing.assert_close(edits["observation"][:, 0], first, atol=1e-5, rtol=1e-5)
    plain = _diffuser(data)
    out = plain.generate(data[:3], sampler=sampler, steps=4, generator=g(), use_ema=False, inpaint_start=True)
    torch.testing.assert_close(out["observation"][:, 0], data["observation"][:3, 0], atol=1e-5, rtol=1e-5)
    # bad input: a start batch of another shape, an unconditional diffuser
    with pytest.raises(ValueError, match=r"'inpaint_start' must be a trajectory batch \[3, 12\]"):
        plain.generate(data[:3], sampler=sampler, steps=2, init=data[:2], use_ema=False, inpaint_start=True)
    with pytest.raises(ValueError, match="unconditional"):
        DiffusionSampler(_diffuser(data, unconditional=True), inpaint_start=True)


def test_objective_guide_climbs_under_an_edit_and_keeps_held_entries(data):
    """The score-guidance hook composes with SDEdit and inpainting: the objective rises against the same draw
    without a guide, the held first observation stays exact, and the sample stays within the clip bounds."""
    d = _diffuser(data)
    cond = data[:6]

    def objective(trajs):  # differentiable in the sample: the mean first observation dim over valid steps
        m = trajs["mask"].float()
        return (trajs["observation"][..., 0] * m).sum(-1) / m.sum(-1).clamp(min=1)

    def draw(scale):
        return d.generate(cond, sampler="ddim", steps=6, generator=torch.Generator().manual_seed(3), use_ema=False,
                          init=cond, strength=0.5, inpaint_start=True, guide=objective, guide_scale=scale)

    plain, guided = draw(0.0), draw(1.0)
    with torch.no_grad():
        assert float(objective(guided).mean()) > float(objective(plain).mean()) + 0.05
    torch.testing.assert_close(guided["observation"][:, 0], cond["observation"][:, 0], atol=1e-5, rtol=1e-5)
    low, high = d.normalizer.unnormalize(d._full(d.x0_bounds()[0][:-1])), d.normalizer.unnormalize(
        d._full(d.x0_bounds()[1][:-1]))
    obs = guided["observation"][guided["mask"]]
    assert bool((obs >= low[:3] - 1e-4).all() and (obs <= high[:3] + 1e-4).all())


def test_parse_overrides_reads_yaml_values_and_rejects_bare_keys():
    assert parse_overrides(["score_condition=true", "hidden_dim=16", "name=a=b"]) == {
        "score_condition": True, "hidden_dim": 16, "name": "a=b"}
    with pytest.raises(ValueError, match="KEY=VALUE.*'score_condition'"):
        parse_overrides(["score_condition"])
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_overrides(["=1"])


def test_a_checkpoint_rebuilds_the_model_it_was_trained_as_after_a_preset_is_retuned(data, tmp_path, monkeypatch):
    """``diffuser.config`` holds the resolved model section: a saved diffuser loads with the prediction type,
    schedule and clip margin it was trained with, even after the preset changed them (it loaded the new values
    without error), and samples exactly as before."""
    import torchrl_ftb.diffusion.presets as presets

    d = _diffuser(data)
    path = save_diffuser(d, tmp_path / "d.pt")
    retuned = {**presets.PRESETS["tiny"], "model": {**presets.PRESETS["tiny"]["model"],
                                                    "prediction_type": "v_prediction", "clip_margin": None,
                                                    "beta_schedule": "linear"}}
    monkeypatch.setitem(presets.PRESETS, "tiny", retuned)
    back = load_diffuser(path)
    assert back.process.prediction_type == d.process.prediction_type != "v_prediction"
    assert back.clip_margin == d.clip_margin is not None
    assert _same_samples(d, back, data[:2])


def test_an_unfitted_unconditional_diffuser_refuses_to_sample():
    """Its bounds are infinite before ``fit_normalizer``: sampling raised nothing and decoded NaN."""
    d = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, unconditional=True)
    with pytest.raises(ValueError, match="the normalizer is not fitted"):
        d.generate(num_samples=2, sampler="ddim", steps=2)


def test_masked_norm_makes_the_condition_embedding_independent_of_its_padding():
    """By default the encoder's GroupNorm and second convolution see the padding: the same 8 valid steps embed
    differently at horizon 8 and 16. With ``masked_norm`` (``encoder_masked_norm``) they embed the same, and the
    option travels with the diffuser's checkpoint."""
    torch.manual_seed(0)
    x = torch.randn(2, 8, 5)
    padded = torch.cat([x, torch.zeros(2, 8, 5)], 1)
    mask8, mask16 = torch.ones(2, 8, dtype=torch.bool), torch.cat([torch.ones(2, 8), torch.zeros(2, 8)], 1).bool()
    for masked in (False, True):
        enc = TrajectoryEncoder(5, embed_dim=16, masked_norm=masked)
        with torch.no_grad():
            short, long = enc(x, mask8)[0], enc(padded, mask16)[0][:, :8]
        assert torch.allclose(short, long, atol=1e-5) == masked
    d = make_diffuser("tiny", obs_dim=3, action_dim=2, horizon=H, encoder_masked_norm=True)
    assert d.encoder.masked_norm and d.config["encoder_masked_norm"] is True
