"""System 3: eq. 2-3 feature shapes, exactly one UNet pass per inference, nothing past the last used
up-block, and the eq. (1) video loss."""

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from trivla_drake.nn import noise_schedule
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA


@pytest.fixture(scope="module")
def model():
    return TriVLA(make_config("tiny")).eval()


def _count_calls(modules):
    counts = [0] * len(modules)
    hooks = [
        m.register_forward_pre_hook(lambda *a, i=i: counts.__setitem__(i, counts[i] + 1))
        for i, m in enumerate(modules)
    ]
    return counts, hooks


def test_feature_shapes_follow_eq_2_3(model):
    dyn = model.dynamics
    cfg = dyn.config
    reversed_channels = list(reversed(cfg.unet.block_out_channels))
    assert dyn.feature_up_block_channels == reversed_channels[: cfg.feature_up_blocks]
    obs = example_observation()
    features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=0)
    expected = (cfg.num_frames, sum(reversed_channels[: cfg.feature_up_blocks]), cfg.feature_size, cfg.feature_size)
    assert set(features) == {"static", "wrist"}
    for view in features.values():
        assert view.shape == expected and view.dtype == np.float32 and np.isfinite(view).all()
    assert not np.allclose(features["static"], features["wrist"])
    cpu = make_config("cpu").dynamics
    cpu_channels = sum(list(reversed(cpu.unet.block_out_channels))[: cpu.feature_up_blocks])
    assert (cpu.num_frames, cpu_channels, cpu.feature_size, cpu.feature_size) == (5, 128, 8, 8)


def test_one_unet_pass_per_inference_and_nothing_past_the_last_used_up_block(model):
    unet = model.dynamics.unet
    used = model.dynamics.config.feature_up_blocks
    assert used < len(unet.up_blocks)  # the tiny preset has an up-block that must stay idle
    watched = [unet, *unet.up_blocks, unet.conv_norm_out, unet.conv_out, model.dynamics.vae.decoder]
    counts, hooks = _count_calls(watched)
    try:
        model.predict_action_chunk(example_observation(), seed=3)
    finally:
        for h in hooks:
            h.remove()
    unet_calls, up_calls, norm_out, conv_out, decoder = counts[0], counts[1:-3], counts[-3], counts[-2], counts[-1]
    assert unet_calls == 1
    assert up_calls == [1] * used + [0] * (len(unet.up_blocks) - used)
    assert norm_out == conv_out == decoder == 0


def test_features_equal_the_full_unet_up_block_outputs(model):
    """The early-stopped read-out gives the same up-block outputs as a full UNet forward."""
    dyn = model.dynamics
    frames = torch.from_numpy(example_observation()["static_rgb"])[None]
    ids = model._dyn_instruction_ids(["open the drawer"], "instruction")
    with torch.no_grad():
        features = dyn(frames, ids, generator=torch.Generator().manual_seed(5))  # unused: fixed noise
        # Rebuild the same UNet input by hand and run the whole UNet, recording the up-blocks.
        condition = dyn.encode_frames(frames).mode()
        sigma = torch.tensor([dyn.config.sigma_max])
        eps = torch.randn(
            (1, dyn.num_frames, *condition.shape[1:]),
            generator=torch.Generator().manual_seed(dyn.config.feature_noise_seed),
        )
        sample = dyn._unet_input(noise_schedule.c_in(sigma) * sigma * eps, condition)
        recorded = []
        hooks = [b.register_forward_hook(lambda m, a, o: recorded.append(o)) for b in dyn.unet.up_blocks]
        try:
            full = dyn.unet(sample, noise_schedule.c_noise(sigma), dyn.encode_text(ids), dyn.added_time_ids(1))
        finally:
            for h in hooks:
                h.remove()
    assert full.sample.shape == (1, dyn.num_frames, dyn.vae.config.latent_channels, dyn.latent_size, dyn.latent_size)
    size = dyn.config.feature_size
    expected = torch.cat(
        [F.interpolate(o, size=(size, size), mode="bilinear") for o in recorded[: dyn.config.feature_up_blocks]], 1
    ).unflatten(0, (1, dyn.num_frames))
    torch.testing.assert_close(features, expected)


def test_fixed_noise_features_depend_on_the_frame_alone(model):
    """Default feature_noise="fixed": the same frame gives the same F_p whatever the seed, and a frame's
    features do not depend on what else is in the batch; different frames give different features."""
    obs = example_observation()
    a = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=11)
    b = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=12)
    assert model.config.dynamics.feature_noise == "fixed"
    assert np.array_equal(a["static"], b["static"]) and np.array_equal(a["wrist"], b["wrist"])
    other = example_observation(seed=5)
    c = model.encode_dynamics(other["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=11)
    assert not np.allclose(a["static"], c["static"])
    frames = torch.from_numpy(np.stack([obs["static_rgb"], other["static_rgb"]]))
    ids = model._dyn_instruction_ids([obs["instruction"]] * 2, "instruction")
    with torch.no_grad():
        batched = model.dynamics(frames, ids)
    torch.testing.assert_close(batched[0], torch.from_numpy(a["static"]), rtol=1e-4, atol=1e-5)


def test_random_noise_features_follow_the_seed():
    model = TriVLA(make_config("tiny")).eval()
    model.dynamics.config.feature_noise = "random"
    obs = example_observation()
    a = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=11)
    b = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=11)
    c = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=12)
    assert np.array_equal(a["static"], b["static"]) and np.array_equal(a["wrist"], b["wrist"])
    assert not np.allclose(a["static"], c["static"])


def test_unknown_feature_noise_is_rejected():
    with pytest.raises(ValueError, match="dynamics.feature_noise"):
        TriVLA(make_config("tiny", dynamics=dataclasses.replace(make_config("tiny").dynamics, feature_noise="gauss")))


def test_video_loss_reconstructs_clips_and_trains_only_the_unet_side(model):
    dyn = model.dynamics
    rng = np.random.default_rng(0)
    video = torch.from_numpy(rng.integers(0, 256, (2, dyn.num_frames, 224, 224, 3), dtype=np.uint8))
    batch = {"video": video, "instruction": ["open the drawer", "lift the block"]}
    model.zero_grad()
    loss, info = model.compute_video_loss(batch, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and loss.item() > 0 and info["video_loss"] == pytest.approx(loss.item())
    loss.backward()
    assert dyn.unet.conv_out.weight.grad.abs().sum() > 0
    assert dyn.text_projection.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in dyn.vae.parameters())
    assert all(p.grad is None for p in dyn.text_encoder.parameters())
    model.zero_grad()
    loss2, _ = model.compute_video_loss(batch, generator=torch.Generator().manual_seed(0))
    assert loss2.item() == pytest.approx(loss.item())
    with pytest.raises(ValueError, match="frames"):
        model.compute_video_loss({**batch, "video": video[:, :2]})


def test_eq1_denoiser_recovers_x0_from_the_v_prediction_target():
    """With SVD's v-prediction preconditioning, D = c_skip x + c_out F equals x_0 exactly when F is the
    standard v target alpha eps - sigma_vp x_0, so eq. (1) regresses the network's D on x_0."""
    s = torch.tensor([0.01, 0.5, 3.0, 700.0])[:, None]
    x0, eps = torch.randn(4, 8), torch.randn(4, 8)
    noisy = x0 + s * eps
    alpha, sigma_vp = 1 / torch.sqrt(s**2 + 1), s / torch.sqrt(s**2 + 1)
    v_target = alpha * eps - sigma_vp * x0
    denoised = noise_schedule.c_skip(s) * noisy + noise_schedule.c_out(s) * v_target
    torch.testing.assert_close(denoised, x0, atol=1e-4, rtol=1e-4)
    # The network input c_in x is eq. (1)'s sqrt(abar) x_0 + sqrt(1 - abar) eps.
    abar = noise_schedule.alpha_bar(s)
    torch.testing.assert_close(noise_schedule.c_in(s) * noisy, abar.sqrt() * x0 + (1 - abar).sqrt() * eps)


def test_one_step_clip_prediction_for_inspection(model):
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (224, 224, 3), dtype=np.uint8)
    clip = model.predict_video(frame, "lift the red block", seed=3)
    size = model.config.dynamics.video_size
    assert clip.shape == (model.dynamics.num_frames, size, size, 3) and clip.dtype == np.uint8
    np.testing.assert_array_equal(clip, model.predict_video(frame, "lift the red block", seed=3))
    assert not np.array_equal(clip, model.predict_video(frame, "lift the red block", seed=4))
    with pytest.raises(ValueError, match="rgb"):
        model.predict_video(frame[:100], "lift the red block")
