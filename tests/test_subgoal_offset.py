"""System 1's sub-goal offset: the instruction grounding's sub-goal seen from the tool-centre point,
added to the state token. It starts at zero, reads only the difference, does not train the grounding,
needs the robot state at inference, and its settings are refused naming the field when they cannot work."""

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.config_io import with_flags
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.policy import SubgoalOffsetEncoder
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig


def _config(offset: bool):
    config = make_config("tiny")
    return dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, subgoal_offset=offset))


def _open_gates(model):
    """AdaLN-Zero: a new DiT's gates are closed, so Q_s reaches no action token until trained."""
    for block in model.policy.dit.blocks:
        torch.nn.init.normal_(block.modulation[1].weight, std=0.5)


def test_the_encoder_starts_at_zero_and_reads_only_the_difference():
    torch.manual_seed(0)
    encoder = SubgoalOffsetEncoder(16)
    subgoal, tcp = torch.randn(4, 3), torch.randn(4, 3)
    assert torch.equal(encoder(subgoal, tcp), torch.zeros(4, 16))
    torch.nn.init.normal_(encoder.mlp[2].weight)
    shift = torch.tensor([0.3, -0.2, 0.1])
    torch.testing.assert_close(encoder(subgoal + shift, tcp + shift), encoder(subgoal, tcp))
    assert not torch.allclose(encoder(subgoal + shift, tcp), encoder(subgoal, tcp))
    # flow matching does not move the grounding through the offset
    subgoal.requires_grad_(True)
    encoder(subgoal, tcp).sum().backward()
    assert subgoal.grad is None


def test_a_new_offset_changes_no_action_and_then_moves_them_with_the_state():
    grounded = TriVLA(_config(False)).eval()
    with_offset = TriVLA(_config(True)).eval()
    missing, unexpected = with_offset.load_state_dict(grounded.state_dict(), strict=False)
    assert not unexpected and missing and all(name.startswith("policy.subgoal_offset.") for name in missing)
    obs = example_observation()
    np.testing.assert_array_equal(with_offset.predict_action_chunk(obs, seed=3), grounded.predict_action_chunk(obs, seed=3))
    torch.nn.init.normal_(with_offset.policy.subgoal_offset.mlp[2].weight, std=1.0)
    _open_gates(with_offset)
    q_vl, q_s = with_offset.encode_vision_language(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    features = with_offset.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=3)
    moved = obs["state"].copy()
    moved[0] += 0.5  # joint 1 turns: the tcp, and so the sub-goal seen from it, moves
    a = with_offset.sample_actions(q_vl, q_s, features, seed=3, state=obs["state"])
    b = with_offset.sample_actions(q_vl, q_s, features, seed=3, state=moved)
    assert not np.allclose(a, b)
    np.testing.assert_array_equal(a, with_offset.predict_action_chunk(obs, seed=3))


def test_system1_with_an_offset_needs_the_state_and_trains_the_offset():
    model = TriVLA(_config(True)).eval()
    _open_gates(model)
    obs = example_observation()
    q_vl, q_s = model.encode_vision_language(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=0)
    with pytest.raises(ValueError, match="state is required.*subgoal_offset"):
        model.sample_actions(q_vl, q_s, features, seed=0)
    with pytest.raises(ValueError, match="state must have shape"):
        model.sample_actions(q_vl, q_s, features, seed=0, state=np.zeros(3))
    pol = model.config.policy
    batch = {
        "static_rgb": np.stack([obs["static_rgb"]] * 2), "wrist_rgb": np.stack([obs["wrist_rgb"]] * 2),
        "instruction": ["lift the red block", "open the drawer"],
        "state": torch.zeros(2, pol.state_dim),
        "action": torch.zeros(2, pol.action_horizon, pol.action_dim),
        "subgoal_position": torch.tensor([[0.5, 0.1, 0.03], [0.4, -0.2, 0.2]]),
    }
    loss, _ = model.compute_loss(batch, generator=torch.Generator().manual_seed(0))
    loss.backward()
    assert model.policy.subgoal_offset.mlp[2].weight.grad.abs().sum() > 0


def test_an_offset_without_grounding_or_tcp_features_is_refused_naming_the_field(tmp_path):
    config = make_config("tiny")
    with pytest.raises(ValueError, match="policy.subgoal_offset.*instruction_grounding and policy.tcp_features"):
        dataclasses.replace(config, policy=dataclasses.replace(config.policy, subgoal_offset=True))
    with pytest.raises(ValueError, match="policy.subgoal_offset.*tcp_features"):
        dataclasses.replace(config, policy=dataclasses.replace(
            config.policy, instruction_grounding=True, tcp_features=False, subgoal_offset=True))
    data = str(tmp_path)
    for stage in ("policy", "video"):
        settings = TrainConfig(stage=stage, data=data, out=str(tmp_path / "o"))
        with pytest.raises(ValueError, match=r"policy.subgoal_offset"):
            with_flags(settings, {"policy.subgoal_offset": True}).resolved().validate()
