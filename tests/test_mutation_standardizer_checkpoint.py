"""A checkpoint keeps System 1's fitted feature statistics: saved, loaded, and used by the loaded model.

The shared checkpoint fixture leaves the statistics at their defaults (mean 0, std 1), which a fresh model
has too, so a loader that dropped them passed every fast test. Here they are fitted to values no fresh
model has, and they change the model's actions.
"""

import numpy as np
import pytest
import torch

from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.checkpoint import WEIGHT_DTYPES, load_checkpoint, save_checkpoint
from trivla_drake.nn.feature_standardizer import FeatureStandardizer
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA


def _standardizers(model):
    """name -> FeatureStandardizer of every standardiser in the model."""
    return {name: module for name, module in model.named_modules() if isinstance(module, FeatureStandardizer)}


@pytest.fixture(scope="module")
def fitted():
    """(model, its actions before fitting, after fitting): a tiny TriVLA with non-default feature statistics."""
    model = TriVLA(make_config("tiny", init_seed=6)).eval()
    observation = example_observation(image_size=model.image_size)
    identity_actions = model.predict_action_chunk(observation, seed=5)
    generator = torch.Generator().manual_seed(7)
    standardizers = _standardizers(model)
    assert len(standardizers) >= 2, list(standardizers)  # System 2's tokens and System 3's features
    for standardizer in standardizers.values():
        standardizer.fit(torch.randn(standardizer.shape, generator=generator),
                         0.5 + torch.rand(standardizer.shape, generator=generator))
    return model, identity_actions, model.predict_action_chunk(observation, seed=5)


@pytest.mark.parametrize("weights_dtype", ["float32", "float16"])
def test_fitted_feature_statistics_survive_save_and_load(fitted, tmp_path, weights_dtype):
    model, identity_actions, fitted_actions = fitted
    assert not np.allclose(identity_actions, fitted_actions, atol=1e-3)  # the statistics matter to the actions
    save_checkpoint(model, str(tmp_path), weights_dtype=weights_dtype)
    loaded = load_checkpoint(str(tmp_path)).eval()

    stored = WEIGHT_DTYPES[weights_dtype]
    loaded_standardizers = _standardizers(loaded)
    assert loaded_standardizers.keys() == _standardizers(model).keys()
    for name, standardizer in _standardizers(model).items():
        for buffer in ("mean", "std"):
            expected = getattr(standardizer, buffer).to(stored).float()  # as stored, cast back to float32
            got = getattr(loaded_standardizers[name], buffer)
            assert torch.equal(got, expected), f"{name}.{buffer} changed on save/load ({weights_dtype})"
    if weights_dtype == "float32":
        observation = example_observation(image_size=model.image_size)
        np.testing.assert_array_equal(loaded.predict_action_chunk(observation, seed=5), fitted_actions)
