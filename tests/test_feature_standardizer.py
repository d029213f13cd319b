"""System 1's standardisation of the frozen features: statistics, floors, sequence positions, the
model's use of them, and checkpoints saved before they existed."""

import pytest
import torch
from safetensors.torch import load_file, save_file

from trivla_drake.nn.checkpoint import load_checkpoint, save_checkpoint
from trivla_drake.nn.feature_standardizer import (
    STD_FLOOR_FRACTION,
    FeatureStandardizer,
    MomentAccumulator,
    SequenceStandardizer,
)
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA


def test_fitted_statistics_standardise_the_samples_and_floor_constant_elements():
    gen = torch.Generator().manual_seed(0)
    x = 5.0 + 0.01 * torch.randn(200, 3, 4, generator=gen)  # small variation on a large constant
    x[:, 0, 0] = 7.0  # an element that never changes
    acc = MomentAccumulator((3, 4))
    acc.add(x[:120])
    acc.add(x[120:])
    mean, std = acc.mean_std()
    torch.testing.assert_close(mean, x.mean(0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(std, x.std(0, unbiased=False), rtol=1e-3, atol=1e-6)
    standardizer = FeatureStandardizer((3, 4))
    torch.testing.assert_close(standardizer(x), x)  # identity until fitted
    standardizer.fit(mean, std)
    z = standardizer(x)
    assert torch.isfinite(z).all() and z[:, 0, 0].abs().max() < 1e-3  # floored std, no blow-up
    assert z[:, 1:].mean(0).abs().max() < 1e-3 and (z[:, 1:].std(0) - 1).abs().max() < 0.02
    assert float(standardizer.std.min()) == pytest.approx(STD_FLOOR_FRACTION * float(std.mean()), rel=1e-4)


def test_fit_rejects_bad_statistics():
    standardizer = FeatureStandardizer((2, 3))
    with pytest.raises(ValueError, match=r"feature mean must have shape \(2, 3\)"):
        standardizer.fit(torch.zeros(3, 2), torch.ones(2, 3))
    with pytest.raises(ValueError, match="feature std has non-finite"):
        standardizer.fit(torch.zeros(2, 3), torch.full((2, 3), float("nan")))
    with pytest.raises(ValueError, match="no samples"):
        MomentAccumulator((2, 3)).mean_std()


def test_sequence_positions_past_the_fixed_head_share_the_last_row():
    standardizer = SequenceStandardizer(positions=2, dim=3)
    standardizer.fit(torch.tensor([[1.0] * 3, [2.0] * 3, [3.0] * 3]), torch.ones(3, 3))
    out = standardizer(torch.zeros(1, 5, 3))
    assert out[0, :, 0].tolist() == [-1.0, -2.0, -3.0, -3.0, -3.0]


def test_system1_reads_standardised_features():
    """Shifting a feature by its fitted mean and scaling by its std leaves System 1's memory unchanged."""
    model = TriVLA(make_config("tiny", init_seed=1)).eval()
    policy = model.policy
    gen = torch.Generator().manual_seed(2)
    q_vl = torch.randn(2, policy.vl_standardizer.positions + 4, model.vision_language.hidden_size, generator=gen)
    static, wrist = (torch.randn(2, *model.dynamics.feature_shape, generator=gen) for _ in range(2))
    with torch.no_grad():
        q_s = torch.zeros(2, policy.config.hidden_size)
        before = policy.conditions(q_s, q_vl, None, policy.aggregate_dynamics(static, wrist))[1]
        shape_vl, shape_dyn = policy.vl_standardizer.shape, policy.dynamics_standardizers[0].shape
        mean_vl, std_vl = torch.randn(shape_vl, generator=gen), torch.rand(shape_vl, generator=gen) + 0.5
        mean_d, std_d = torch.randn(shape_dyn, generator=gen), torch.rand(shape_dyn, generator=gen) + 0.5
        policy.vl_standardizer.fit(mean_vl, std_vl)
        for s in policy.dynamics_standardizers:
            s.fit(mean_d, std_d)
        index = torch.arange(q_vl.shape[1]).clamp_max(policy.vl_standardizer.positions)
        moved_vl = q_vl * std_vl[index] + mean_vl[index]
        after = policy.conditions(q_s, moved_vl, None, policy.aggregate_dynamics(static * std_d + mean_d,
                                                                                  wrist * std_d + mean_d))[1]
    torch.testing.assert_close(after, before, rtol=1e-4, atol=1e-4)


def test_checkpoints_from_before_standardisation_load_with_identity_statistics(tmp_path):
    model = TriVLA(make_config("tiny", init_seed=4)).eval()
    save_checkpoint(model, str(tmp_path))
    weights = tmp_path / "model.safetensors"
    state = {k: v for k, v in load_file(str(weights)).items() if "standardizer" not in k}
    save_file(state, str(weights), metadata={"format": "pt"})
    loaded = load_checkpoint(str(tmp_path))
    assert float(loaded.policy.vl_standardizer.mean.abs().max()) == 0.0
    assert float((loaded.policy.dynamics_standardizers[1].std - 1).abs().max()) == 0.0
