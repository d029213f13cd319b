"""The whole model: action chunks, the split inference API, seeding, ablations, losses, bad input."""

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.normalization import NormalizationStats
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA




@pytest.fixture(scope="module")
def model():
    return TriVLA(make_config("tiny")).eval()


@pytest.fixture
def obs():
    return example_observation()


def test_predict_action_chunk_shape_and_dtype(model, obs):
    chunk = model.predict_action_chunk(obs, seed=0)
    assert chunk.shape == (10, 7) and chunk.dtype == np.float32 and np.isfinite(chunk).all()


def test_seeded_inference_is_reproducible_and_seeds_matter(model, obs):
    a = model.predict_action_chunk(obs, seed=7)
    assert np.array_equal(a, model.predict_action_chunk(obs, seed=7))
    assert not np.allclose(a, model.predict_action_chunk(obs, seed=8))
    # the global RNG is neither needed nor disturbed by seeded calls
    state = torch.random.get_rng_state()
    model.predict_action_chunk(obs, seed=7)
    assert torch.equal(state, torch.random.get_rng_state())


def test_split_api_composes_to_predict_action_chunk(model, obs):
    q_vl, q_s = model.encode_vision_language(
        obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"], obs["embodiment_id"]
    )
    features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=4)
    vl = model.vision_language
    assert q_vl.dtype == np.float32 and q_vl.ndim == 2 and q_vl.shape[1] == vl.hidden_size
    assert q_vl.shape[0] > 2 * vl.num_image_tokens  # both views' tokens plus the prompt
    assert q_s.shape == (model.config.policy.hidden_size,)
    actions = model.sample_actions(q_vl, q_s, features, seed=4, embodiment_id=obs["embodiment_id"])
    np.testing.assert_array_equal(actions, model.predict_action_chunk(obs, seed=4))
    np.testing.assert_array_equal(q_s, model.encode_state(obs["state"], obs["embodiment_id"]))
    # torch inputs work too
    torch_actions = model.sample_actions(
        torch.from_numpy(q_vl), torch.from_numpy(q_s), {k: torch.from_numpy(v) for k, v in features.items()}, seed=4
    )
    np.testing.assert_array_equal(actions, torch_actions)
    # the intermediate results are small
    assert q_vl.nbytes + sum(v.nbytes for v in features.values()) < 2_000_000


def test_embodiment_id_selects_different_weights(model, obs):
    a = model.predict_action_chunk({**obs, "embodiment_id": 0}, seed=1)
    b = model.predict_action_chunk({**obs, "embodiment_id": 1}, seed=1)
    assert not np.allclose(a, b)


def test_more_euler_steps_are_configurable(model, obs):
    calls = []
    hook = model.policy.dit.register_forward_pre_hook(lambda *a: calls.append(1))
    try:
        model.predict_action_chunk(obs, seed=0, num_steps=7)
    finally:
        hook.remove()
    assert len(calls) == 7


def test_actions_are_unnormalised_with_the_carried_statistics(obs):
    config = make_config("tiny")
    stats = NormalizationStats(
        state_mean=list(np.linspace(-1, 1, 18)),
        state_std=[2.0] * 18,
        action_min=[10.0] * 7,
        action_max=[12.0] * 7,
    )
    normalised = TriVLA(config).eval()
    scaled = TriVLA(config, normalization=stats).eval()
    assert scaled.normalization == stats
    shifted = {**obs, "state": obs["state"] * 2.0 + np.linspace(-1, 1, 18)}
    a = normalised.predict_action_chunk(obs, seed=3)
    b = scaled.predict_action_chunk(shifted, seed=3)
    np.testing.assert_allclose(b, (a + 1.0) * 0.5 * 2.0 + 10.0, rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="action_min"):
        scaled.set_normalization(dataclasses.replace(stats, action_min=[0.0] * 6))


@pytest.mark.parametrize("use2, use3", [(False, False), (False, True), (True, False)])
def test_ablations_drop_systems(use2, use3, obs):
    model = TriVLA(make_config("tiny", use_system2=use2, use_system3=use3)).eval()
    counts = model.parameter_counts()
    assert (counts["system2"] > 0) == use2 and (counts["system3"] > 0) == use3 and counts["system1"] > 0
    chunk = model.predict_action_chunk(obs, seed=0)
    assert chunk.shape == (10, 7) and np.isfinite(chunk).all()
    q_vl, q_s = model.encode_vision_language(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=0)
    assert (q_vl.size > 0) == use2 and bool(features) == use3
    np.testing.assert_array_equal(model.sample_actions(q_vl if use2 else None, q_s, features, seed=0), chunk)


def test_parameter_counts_add_up(model):
    counts = model.parameter_counts()
    assert counts["total"] == sum(p.numel() for p in model.parameters())
    assert counts["total"] == counts["system1"] + counts["system2"] + counts["system3"]


def _training_batch(model, b=2, seed=0):
    rng = np.random.default_rng(seed)
    pol = model.config.policy
    return {
        "static_rgb": torch.from_numpy(rng.integers(0, 256, (b, 224, 224, 3), dtype=np.uint8)),
        "wrist_rgb": torch.from_numpy(rng.integers(0, 256, (b, 224, 224, 3), dtype=np.uint8)),
        "instruction": ["open the drawer", "lift the red block"][:b],
        "state": torch.from_numpy(rng.normal(size=(b, pol.state_dim)).astype(np.float32)),
        "action": torch.from_numpy(rng.uniform(-1, 1, (b, pol.action_horizon, pol.action_dim)).astype(np.float32)),
        "embodiment_id": torch.tensor([0, 1][:b]),
    }


def test_compute_loss_trains_system1_only_by_default(model):
    batch = _training_batch(model)
    model.zero_grad()
    loss, info = model.compute_loss(batch, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and set(info) >= {"loss", "flow_time_mean"}
    loss.backward()
    assert model.policy.action_decoder.fc2.weight.grad.abs().sum() > 0
    assert model.policy.vl_proj.weight.grad.abs().sum() > 0
    assert model.policy.video_former.queries.grad.abs().sum() > 0
    assert all(p.grad is None for p in model.vision_language.parameters())
    assert all(p.grad is None for p in model.dynamics.parameters())
    model.zero_grad()


def test_compute_loss_accepts_precomputed_features_and_padding(model):
    batch = _training_batch(model)
    with torch.no_grad():
        q_vl, mask = model.encode_vision_language_batch(batch["static_rgb"], batch["wrist_rgb"], batch["instruction"])
        f_static, f_wrist = model.encode_dynamics_batch(
            batch["static_rgb"], batch["wrist_rgb"], batch["instruction"], generator=torch.Generator().manual_seed(1)
        )
    pre = {k: batch[k] for k in ("state", "action", "embodiment_id")}
    pre.update(q_vl=q_vl, q_vl_mask=mask, dynamics_static=f_static, dynamics_wrist=f_wrist)
    loss_a, _ = model.compute_loss(pre, generator=torch.Generator().manual_seed(0))
    loss_b, _ = model.compute_loss(pre, generator=torch.Generator().manual_seed(0))
    assert loss_a.item() == loss_b.item()
    pad = torch.zeros(2, 10, dtype=torch.bool)
    pad[:, 5:] = True
    loss_c, _ = model.compute_loss({**pre, "action_is_pad": pad}, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(loss_c) and loss_c.item() != loss_a.item()
    # Entries after a disturbed step (DART) are left out like padding, alone or together with it.
    tail, middle = torch.zeros(2, 10, dtype=torch.bool), torch.zeros(2, 10, dtype=torch.bool)
    tail[:, 7:], middle[:, 5:7] = True, True  # together the same entries as `pad`
    loss_d, _ = model.compute_loss({**pre, "action_is_stale": pad}, generator=torch.Generator().manual_seed(0))
    loss_e, _ = model.compute_loss({**pre, "action_is_pad": tail, "action_is_stale": middle},
                                   generator=torch.Generator().manual_seed(0))
    assert loss_d.item() == loss_c.item() == loss_e.item()
    with pytest.raises(ValueError, match="action"):
        model.compute_loss({**pre, "action": pre["action"][:, :5]})
    with pytest.raises(ValueError, match="state"):
        model.compute_loss({**pre, "state": torch.full((2, 18), float("nan"))})
    with pytest.raises(ValueError, match="embodiment_id"):
        model.compute_loss({**pre, "embodiment_id": torch.tensor([0, 5])})


def test_compute_loss_decreases_when_overfitting():
    local = TriVLA(make_config("tiny", use_system2=False, use_system3=False))
    batch = _training_batch(local)

    def held_out_loss():  # the same noise and flow times each time
        with torch.no_grad():
            return local.compute_loss(batch, generator=torch.Generator().manual_seed(123))[0].item()

    before = held_out_loss()
    opt = torch.optim.Adam(local.parameters(), lr=3e-3)
    gen = torch.Generator().manual_seed(0)
    for _ in range(60):
        loss, _ = local.compute_loss(batch, generator=gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert held_out_loss() < 0.5 * before


# ---------------------------------------------------------------------------------------------- bad input


def _bad(obs, **changes):
    out = dict(obs)
    for key, value in changes.items():
        if value is _DELETE:
            del out[key]
        else:
            out[key] = value
    return out


_DELETE = object()


@pytest.mark.parametrize(
    "changes, field",
    [
        (dict(static_rgb=np.zeros((128, 128, 3), np.uint8)), "static_rgb"),
        (dict(wrist_rgb=np.zeros((224, 224, 3), np.float32)), "wrist_rgb"),
        (dict(static_rgb=np.zeros((224, 224), np.uint8)), "static_rgb"),
        (dict(wrist_rgb=_DELETE), "wrist_rgb"),
        (dict(wrist_rgb=None), "wrist_rgb"),
        (dict(state=np.full(18, np.nan)), "state"),
        (dict(state=np.zeros(17)), "state"),
        (dict(instruction=""), "instruction"),
        (dict(instruction="   "), "instruction"),
        (dict(instruction="pick " * 40), "instruction"),
        (dict(instruction=None), "instruction"),
        (dict(embodiment_id=2), "embodiment_id"),
        (dict(embodiment_id=-1), "embodiment_id"),
        (dict(embodiment_id="panda"), "embodiment_id"),
    ],
)
def test_bad_observations_raise_value_errors_naming_the_field(model, obs, changes, field):
    with pytest.raises(ValueError, match=field):
        model.predict_action_chunk(_bad(obs, **changes), seed=0)


def test_bad_split_api_inputs_are_named(model, obs):
    with pytest.raises(ValueError, match="static_rgb"):
        model.encode_dynamics(obs["static_rgb"][:100], obs["wrist_rgb"], "go", seed=0)
    with pytest.raises(ValueError, match="state"):
        model.encode_vision_language(obs["static_rgb"], obs["wrist_rgb"], "go", np.array([np.inf] * 18))
    q_vl, q_s = model.encode_vision_language(obs["static_rgb"], obs["wrist_rgb"], "go", obs["state"])
    features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], "go", seed=0)
    with pytest.raises(ValueError, match="dynamics_features\\['wrist'\\]"):
        model.sample_actions(q_vl, q_s, {"static": features["static"]}, seed=0)
    with pytest.raises(ValueError, match="q_vl"):
        model.sample_actions(None, q_s, features, seed=0)
    with pytest.raises(ValueError, match="q_s"):
        model.sample_actions(q_vl, q_s[:-1], features, seed=0)
    with pytest.raises(ValueError, match="embodiment_id"):
        model.sample_actions(q_vl, q_s, features, seed=0, embodiment_id=9)
    with pytest.raises(ValueError, match="observation"):
        model.predict_action_chunk([1, 2, 3])


def test_a_state_dimension_constant_in_the_data_is_not_blown_up_at_test_time():
    """normalize_state floors the std at STATE_STD_FLOOR: a dimension the data never moved (std 0) maps a
    1 mm deviation to 1, not to 1e5."""
    import torch

    from trivla_drake.nn.normalization import STATE_STD_FLOOR, NormalizationStats, Normalizer

    stats = NormalizationStats(state_mean=[0.0, 0.5], state_std=[0.2, 0.0], action_min=[-1.0], action_max=[1.0])
    normalized = Normalizer(stats).normalize_state(torch.tensor([[0.2, 0.501]]))
    assert torch.allclose(normalized, torch.tensor([[1.0, 0.001 / STATE_STD_FLOOR]]), atol=1e-4)
