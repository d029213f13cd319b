"""System 1's sampling noise scale (`TriVLA.set_initial_noise_scale`, inference.noise_scale): 0 gives one
deterministic chunk per observation, 1 (the default) the paper's sampling; bad values are named."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from trivla_drake.eval.evaluate import EvalConfig
from trivla_drake.eval.inference_config import InferenceConfig
from trivla_drake.eval.paper_tables import TablesConfig, _stored
from trivla_drake.eval.policies import load_policy
from trivla_drake.nn import TriVLA, load_checkpoint, make_config, save_checkpoint
from trivla_drake.nn.benchmark import example_observation


@pytest.fixture(scope="module")
def model():
    return TriVLA(make_config("tiny"), load_pretrained=False).eval()


def _chunk(model, scale, seed):
    model.set_initial_noise_scale(scale)
    observation = example_observation(model.image_size, model.config.policy.state_dim)
    return model.predict_action_chunk(observation, seed=seed)


def test_scale_zero_is_deterministic_and_scale_one_is_the_default_sampling(model):
    assert model.initial_noise_scale == 1.0
    default = model.predict_action_chunk(example_observation(model.image_size, model.config.policy.state_dim), seed=1)
    np.testing.assert_array_equal(_chunk(model, 1.0, 1), default)
    assert not np.allclose(_chunk(model, 1.0, 1), _chunk(model, 1.0, 2))  # fresh noise per seed
    np.testing.assert_array_equal(_chunk(model, 0.0, 1), _chunk(model, 0.0, 2))
    assert not np.allclose(_chunk(model, 0.0, 1), default)
    model.set_initial_noise_scale(1.0)


@pytest.mark.parametrize("bad", [-0.5, math.nan, math.inf])
def test_bad_scales_are_named(model, bad):
    with pytest.raises(ValueError, match="noise_scale"):
        model.set_initial_noise_scale(bad)
    assert model.initial_noise_scale == 1.0
    with pytest.raises(ValueError, match="inference.noise_scale"):
        EvalConfig(policy="trivla", tasks=["lift_block"], episodes=1, inference=InferenceConfig(noise_scale=bad)).validate()


def test_the_scale_is_an_inference_setting_not_saved_with_the_weights(model, tmp_path):
    model.set_initial_noise_scale(0.0)
    save_checkpoint(model, str(tmp_path / "ckpt"))
    model.set_initial_noise_scale(1.0)
    assert "noise_scale" not in (tmp_path / "ckpt" / "config.json").read_text()  # checkpoints unchanged
    assert load_checkpoint(str(tmp_path / "ckpt")).initial_noise_scale == 1.0
    policy = load_policy(str(tmp_path / "ckpt"), noise_scale=0.25)  # what each evaluate worker runs
    assert policy.model.initial_noise_scale == 0.25


def test_noise_scale_with_a_policy_that_does_not_sample_is_an_error(capsys):
    from trivla_drake.cli import main

    with pytest.raises(ValueError, match="TriVLA checkpoints only"):
        load_policy("oracle", noise_scale=0.0)
    assert main(["evaluate", "--policy", "random", "--tasks", "lift_block", "--episodes", "1",
                 "--set", "inference.noise_scale=0", "--no-progress"]) == 2
    assert "inference.noise_scale" in capsys.readouterr().err
    assert main(["demo", "--policy", "oracle", "--set", "inference.noise_scale=0"]) == 2
    assert "inference.* and --latency go with --policy trivla" in capsys.readouterr().err


def test_tables_store_results_per_noise_scale_and_thread_count(tmp_path):
    checkpoint = tmp_path / "ckpt"
    checkpoint.mkdir()
    (checkpoint / "config.json").write_text("{}")
    (checkpoint / "model.safetensors").write_bytes(b"weights")
    settings = {"kind": "evaluate", "seed": 0}
    calls = []

    def compute(value):
        return lambda: calls.append(value) or {"value": value}

    default = TablesConfig(results_dir=str(tmp_path / "stored"))
    zero = TablesConfig(results_dir=str(tmp_path / "stored"), inference=InferenceConfig(noise_scale=0))
    assert _stored(default, str(checkpoint), settings, compute("default")) == {"value": "default"}
    assert _stored(zero, str(checkpoint), settings, compute("zero")) == {"value": "zero"}
    assert _stored(default, str(checkpoint), settings, compute("again")) == {"value": "default"}
    zero.inference.noise_scale = 0.0  # the same setting, written as a float
    assert _stored(zero, str(checkpoint), settings, compute("zero again")) == {"value": "zero"}
    two_threads = TablesConfig(results_dir=str(tmp_path / "stored"), threads=2)
    assert _stored(two_threads, str(checkpoint), settings, compute("threads")) == {"value": "threads"}
    assert calls == ["default", "zero", "threads"]
    records = [json.loads(p.read_text())["settings"] for p in (tmp_path / "stored").glob("*.json")]
    assert sorted(map(str, records)) == sorted(map(str, [settings, {**settings, "noise_scale": 0.0},
                                                         {**settings, "threads": 2}]))
