"""Checkpoints that are wrong, incomplete or corrupted are refused at load, naming the file and the field or tensor."""

import json
import logging
import os
import shutil

import pytest
import torch

from trivla_drake.nn.checkpoint import load_checkpoint
from trivla_drake.nn.config import TriVLAConfig
from trivla_drake.nn.config_dict import FIELDS_OLDER_CHECKPOINTS_OMIT, REMOVED_FIELDS, config_from_dict, config_to_dict


def _copy(directory, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(directory, out)
    return out


def _edit_config(out, edit):
    meta = json.loads((out / "config.json").read_text())
    edit(meta)
    (out / "config.json").write_text(json.dumps(meta))


def test_a_missing_config_field_is_refused_naming_it_and_the_file(saved, tmp_path):
    out = _copy(saved[1], tmp_path)
    _edit_config(out, lambda meta: meta["config"]["policy"].pop("num_heads"))
    with pytest.raises(ValueError, match=r"config\.json: config\.policy\.num_heads is missing"):
        load_checkpoint(str(out))
    out = _copy(saved[1], tmp_path / "b")
    _edit_config(out, lambda meta: meta["config"].pop("dynamics"))
    with pytest.raises(ValueError, match=r"config\.dynamics is missing"):
        load_checkpoint(str(out))


def test_an_unknown_config_field_is_refused_naming_the_file(saved, tmp_path):
    out = _copy(saved[1], tmp_path)
    _edit_config(out, lambda meta: meta["config"]["policy"].update(num_headz=2))
    with pytest.raises(ValueError, match=r"config\.json: config\.policy has unknown fields \['num_headz'\]"):
        load_checkpoint(str(out))


def test_fields_newer_than_a_checkpoint_take_the_value_that_reproduces_it(saved, tmp_path):
    """An older checkpoint lacks the fields added since: they take the values it was made with."""
    model, directory = saved
    out = _copy(directory, tmp_path)

    def drop_newer(meta):
        for dotted in ("policy.subgoal_offset", "policy.grounding_reads_gripper", "dynamics.feature_noise"):
            section, name = dotted.split(".")
            meta["config"][section].pop(name)

    _edit_config(out, drop_newer)
    loaded = load_checkpoint(str(out))
    assert loaded.config.dynamics.feature_noise == "random"  # what System 3 drew before the field existed
    assert loaded.config.policy.subgoal_offset is False and loaded.config.policy.grounding_reads_gripper is False


def _holder(data: dict, dotted: str) -> tuple[dict, str]:
    """The dict holding a dotted config field and its name (top-level fields, e.g. text_encoder, have no section)."""
    *sections, name = dotted.split(".")
    return (data[sections[0]] if sections else data), name


def test_every_omittable_field_exists_with_a_valid_value():
    data = config_to_dict(TriVLAConfig())
    for dotted in FIELDS_OLDER_CHECKPOINTS_OMIT:
        holder, name = _holder(data, dotted)
        assert name in holder, dotted
        del holder[name]
    config_from_dict(data)


def test_the_shipped_config_json_holds_every_field_and_loads_unchanged():
    """No field of the shipped checkpoint comes from a default: its config is exactly the file's, but for the
    removed variants' fields, which it lists at their off values, and the fields added since it was saved, which
    take their older-checkpoint values."""
    from trivla_drake.eval.model_loading import default_checkpoint_dir

    meta = json.loads((default_checkpoint_dir() / "config.json").read_text())
    expected = json.loads(json.dumps(meta["config"]))
    for dotted, off in REMOVED_FIELDS.items():
        section, name = dotted.split(".")
        assert expected[section].pop(name) == json.loads(json.dumps(off)), dotted  # listed, and off
    for dotted, value in FIELDS_OLDER_CHECKPOINTS_OMIT.items():
        holder, name = _holder(expected, dotted)
        holder.setdefault(name, json.loads(json.dumps(value)))
    assert json.loads(json.dumps(config_to_dict(config_from_dict(meta["config"])))) == expected


@pytest.mark.parametrize("dotted, on", [("policy.subgoal_yaw", True), ("policy.grounding_reads_tcp", True),
                                        ("policy.grounding_anchor_camera", [0.0] * 12),
                                        ("vision_language.image_token_norm", True)])
def test_a_removed_variant_loads_off_and_is_refused_on_naming_the_field_and_the_tag(saved, tmp_path, dotted, on):
    """A checkpoint listing a removed field at its off value loads (the field ignored); one that turns it on is
    refused, naming the field and the git tag that keeps its code."""
    section, name = dotted.split(".")
    off = _copy(saved[1], tmp_path / "off")
    _edit_config(off, lambda meta: meta["config"][section].update({name: json.loads(json.dumps(REMOVED_FIELDS[dotted]))}))
    assert not hasattr(getattr(load_checkpoint(str(off)).config, section), name)
    turned_on = _copy(saved[1], tmp_path / "on")
    _edit_config(turned_on, lambda meta: meta["config"][section].update({name: on}))
    with pytest.raises(ValueError, match=rf"config\.{dotted.replace('.', '[.]')} is .*research-archive"):
        load_checkpoint(str(turned_on))


def test_a_config_json_without_its_config_is_a_clear_error(saved, tmp_path):
    out = _copy(saved[1], tmp_path)
    _edit_config(out, lambda meta: meta.pop("config"))
    with pytest.raises(ValueError, match=r"config\.json has no 'config' object"):
        load_checkpoint(str(out))
    out2 = _copy(saved[1], tmp_path / "b")
    _edit_config(out2, lambda meta: meta.pop("normalization"))
    with pytest.raises(ValueError, match=r"has no 'normalization' object"):
        load_checkpoint(str(out2))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused_naming_the_tensor(saved, tmp_path, bad):
    from safetensors.torch import load_file, save_file

    out = _copy(saved[1], tmp_path)
    weights = load_file(str(out / "model.safetensors"))
    name = sorted(k for k, v in weights.items() if v.is_floating_point() and v.numel() > 1)[0]
    weights[name] = weights[name].clone()
    weights[name].view(-1)[1] = bad
    save_file(weights, str(out / "model.safetensors"), metadata={"format": "trivla-drake-checkpoint"})
    with pytest.raises(ValueError, match=rf"NaN or infinite weights .*{name.replace('.', '[.]')}"):
        load_checkpoint(str(out))


def test_load_model_refuses_a_missing_default_checkpoint(tmp_path, monkeypatch, caplog):
    from trivla_drake.eval import model_loading

    monkeypatch.setattr(model_loading, "default_checkpoint_dir", lambda: tmp_path / "trivla_cpu")
    with pytest.raises(FileNotFoundError, match=r"default checkpoint is missing.*--preset NAME"):
        model_loading.load_model()
    with caplog.at_level(logging.WARNING):
        model = model_loading.load_model(preset="tiny")  # asked for by name: an untrained model
    assert model.config.preset == "tiny" and "UNTRAINED 'tiny'" in caplog.text
