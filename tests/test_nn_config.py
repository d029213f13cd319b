"""Presets, validation and the JSON round trip of the TriVLA config."""

import dataclasses
import json

import pytest

from trivla_drake.nn.config_dict import config_from_dict, config_to_dict
from trivla_drake.nn.presets import PRESETS, make_config


def test_presets_build_and_default_to_paper_shapes():
    paper = make_config("paper")
    assert paper.vision_language.select_layer == 12
    assert paper.vision_language.vision.image_size == 224 and paper.vision_language.vision.patch_size == 14
    assert paper.vision_language.llm.hidden_size == 2048 and paper.vision_language.llm.num_hidden_layers == 24
    assert paper.dynamics.unet.block_out_channels == (320, 640, 1280, 1280)
    assert paper.policy.action_horizon == 10 and paper.policy.action_dim == 7 and paper.policy.state_dim == 18
    for name in PRESETS:
        config = make_config(name)
        assert config.preset == name
        assert 4 <= config.policy.num_inference_steps <= 10


def test_unknown_preset_lists_valid_ones():
    with pytest.raises(ValueError, match="cpu, cpu_minilm, paper, tiny"):
        make_config("huge")


def test_json_round_trip_is_exact():
    for name in PRESETS:
        config = make_config(name)
        data = json.loads(json.dumps(config_to_dict(config)))
        assert config_from_dict(data) == config


def test_bad_config_fields_are_named():
    data = config_to_dict(make_config("tiny"))
    data["policy"]["bogus"] = 1
    with pytest.raises(ValueError, match="bogus"):
        config_from_dict(data)
    data = config_to_dict(make_config("tiny"))
    data["policy"]["action_dim"] = "seven"
    with pytest.raises(ValueError, match="policy.action_dim"):
        config_from_dict(data)
    config = make_config("tiny")
    with pytest.raises(ValueError, match="select_layer"):
        dataclasses.replace(
            config, vision_language=dataclasses.replace(config.vision_language, select_layer=5)
        )
    with pytest.raises(ValueError, match="action_names"):
        dataclasses.replace(config, policy=dataclasses.replace(config.policy, action_dim=8))
