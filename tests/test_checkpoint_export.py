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
