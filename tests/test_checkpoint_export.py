"""`trivla-drake export`: float16 weights at half the size, the same actions, and a crash never harms the
folder being replaced."""

import os

import numpy as np
import pytest
import torch

from trivla_drake.cli import main
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.checkpoint import load_checkpoint, save_checkpoint


def _size(directory):
    return os.path.getsize(os.path.join(directory, "model.safetensors"))


def test_float16_export_halves_the_file_and_keeps_the_actions(saved, tmp_path, capsys):
    model, directory = saved
    out = tmp_path / "half"
    assert main(["export", directory, "--out", str(out)]) == 0
    assert "weights in float16" in capsys.readouterr().out
    assert _size(out) < 0.52 * _size(directory)
    loaded = load_checkpoint(str(out)).eval()
    assert {p.dtype for p in loaded.parameters()} == {torch.float32}
    assert loaded.normalization == model.normalization
    obs = example_observation()
    full, half = model.predict_action_chunk(obs, seed=2), loaded.predict_action_chunk(obs, seed=2)
    assert not np.array_equal(full, half)  # really rounded
    np.testing.assert_allclose(half, full, atol=2e-2 * max(1.0, float(np.abs(full).max())))


def test_failed_export_leaves_the_existing_target_intact(saved, tmp_path, capsys):
    _, directory = saved
    target = tmp_path / "shipped"
    assert main(["export", directory, "--out", str(target)]) == 0
    before = (target / "model.safetensors").read_bytes()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text(open(os.path.join(directory, "config.json")).read())
    (broken / "model.safetensors").write_bytes(open(os.path.join(directory, "model.safetensors"), "rb").read()[:1000])
    assert main(["export", str(broken), "--out", str(target)]) == 2
    assert "truncated or corrupt" in capsys.readouterr().err
    assert (target / "model.safetensors").read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]


def test_unknown_weights_dtype_names_the_field(saved, tmp_path):
    model, _ = saved
    with pytest.raises(ValueError, match="weights_dtype"):
        save_checkpoint(model, str(tmp_path / "x"), weights_dtype="int8")


def test_export_can_drop_the_llm_layers_above_the_readout_and_keeps_q_vl(tmp_path):
    from trivla_drake.nn.presets import make_config
    from trivla_drake.nn.trivla import TriVLA

    config = make_config("tiny", init_seed=4)
    all_layers, readout = config.vision_language.llm.num_hidden_layers, config.vision_language.select_layer
    assert readout < all_layers
    model = TriVLA(config).eval()
    source = tmp_path / "full"
    save_checkpoint(model, str(source))
    out = tmp_path / "trimmed"
    assert main(["export", str(source), "--out", str(out), "--set", "dtype=float32", "--set", "drop_unused_llm_layers=true"]) == 0
    assert _size(out) < _size(source)
    trimmed = load_checkpoint(str(out)).eval()
    vl = trimmed.vision_language
    assert len(vl.llm.model.layers) == vl.config.select_layer == vl.llm.config.num_hidden_layers
    assert trimmed.config.vision_language.drop_unused_llm_layers
    removed = model.parameter_counts()["system2"] - trimmed.parameter_counts()["system2"]
    layer = sum(p.numel() for p in model.vision_language.llm.model.layers[-1].parameters())
    assert removed == layer * (all_layers - readout)
    obs = example_observation()
    np.testing.assert_array_equal(trimmed.predict_action_chunk(obs, seed=5), model.predict_action_chunk(obs, seed=5))
    # The unchanged source still has every layer (a later --stage vlm needs them).
    assert len(load_checkpoint(str(source)).vision_language.llm.model.layers) == all_layers
