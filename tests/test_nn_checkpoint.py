"""save_checkpoint / load_checkpoint: identical outputs, carried statistics, clear errors."""

import json
import os

import numpy as np
import pytest

from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.checkpoint import load_checkpoint
from trivla_drake.nn.config_dict import config_to_dict
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA






def test_save_then_load_gives_identical_outputs(saved):
    model, directory = saved
    assert sorted(os.listdir(directory)) == ["config.json", "model.safetensors"]
    loaded = load_checkpoint(directory).eval()
    obs = example_observation()
    np.testing.assert_array_equal(model.predict_action_chunk(obs, seed=5), loaded.predict_action_chunk(obs, seed=5))
    assert loaded.normalization == model.normalization
    assert loaded.config == model.config
    # tied LLM embeddings stay tied after loading
    llm = loaded.vision_language.llm
    assert llm.lm_head.weight.data_ptr() == llm.model.embed_tokens.weight.data_ptr()


def test_the_weights_are_as_readable_as_the_config(saved):
    model, directory = saved
    modes = {name: os.stat(os.path.join(directory, name)).st_mode & 0o777 for name in os.listdir(directory)}
    assert modes["model.safetensors"] == modes["config.json"]  # not safetensors' owner-only 0600
    assert modes["model.safetensors"] & 0o044 == 0o644 & ~_umask() & 0o044


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_config_json_describes_the_model(saved):
    model, directory = saved
    with open(os.path.join(directory, "config.json")) as f:
        meta = json.load(f)
    assert meta["preset"] == "tiny"
    assert meta["config"] == json.loads(json.dumps(config_to_dict(model.config)))
    assert meta["action_space"]["dim"] == 7 and meta["action_space"]["horizon"] == 10
    assert meta["action_space"]["names"] == ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]
    assert meta["normalization"] == model.normalization.to_dict()
    assert meta["tokenizers"] == {"vision_language": "byte", "dynamics": "byte"}


def _copy(directory, tmp_path):
    out = tmp_path / "copy"
    out.mkdir()
    for name in os.listdir(directory):
        (out / name).write_bytes(open(os.path.join(directory, name), "rb").read())
    return out


def test_truncated_weights_are_a_value_error(saved, tmp_path):
    out = _copy(saved[1], tmp_path)
    data = (out / "model.safetensors").read_bytes()
    for cut in (len(data) // 2, 40, 4):
        (out / "model.safetensors").write_bytes(data[:cut])
        with pytest.raises(ValueError, match="truncated or corrupt"):
            load_checkpoint(str(out))


def test_config_of_another_preset_is_a_value_error(saved, tmp_path):
    out = _copy(saved[1], tmp_path)
    meta = json.loads((out / "config.json").read_text())
    other = TriVLA(make_config("tiny", use_system3=False))  # a different architecture
    meta["config"] = config_to_dict(other.config)
    meta["component_configs"] = other.component_configs()
    (out / "config.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="does not match the architecture"):
        load_checkpoint(str(out))
    meta["config"] = config_to_dict(make_config("cpu"))
    meta["component_configs"] = {}
    (out / "config.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="shape mismatches"):
        load_checkpoint(str(out))


def test_action_dim_mismatch_is_a_value_error(saved, tmp_path):
    with pytest.raises(ValueError, match="action_dim 7; expected 8"):
        load_checkpoint(saved[1], action_dim=8)
    with pytest.raises(ValueError, match="state_dim"):
        load_checkpoint(saved[1], state_dim=9)
    out = _copy(saved[1], tmp_path)
    meta = json.loads((out / "config.json").read_text())
    meta["config"]["policy"]["action_dim"] = 8
    meta["config"]["action_names"] = [f"a{i}" for i in range(8)]
    meta["normalization"]["action_min"] += [-1.0]
    meta["normalization"]["action_max"] += [1.0]
    (out / "config.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="shape mismatches"):
        load_checkpoint(str(out))


def test_broken_config_json_is_a_value_error(saved, tmp_path):
    out = _copy(saved[1], tmp_path)
    (out / "config.json").write_text("{ not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_checkpoint(str(out))
    (out / "config.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="not a TriVLA checkpoint"):
        load_checkpoint(str(out))
    with pytest.raises(FileNotFoundError):
        load_checkpoint(str(tmp_path / "nowhere"))
