"""The instruction grounding that also reads the tool-centre point (`PolicyConfig.grounding_reads_tcp`):
its sub-goal can then be placed from the wrist view as an offset from the gripper. It needs the robot
state wherever it runs (inference, the bind loss, the checks), says so naming the field, and a run
adds it to a grounded checkpoint keeping the attention it had."""

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.config import make_config
from trivla_drake.nn.instruction_grounding import InstructionGrounding
from trivla_drake.nn.panda_tcp import FEATURE_DIM as TCP_FEATURE_DIM
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.trainer import apply_ablations


def _config(reads_tcp: bool, offset: bool = False):
    config = make_config("tiny")
    return dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, grounding_reads_tcp=reads_tcp,
        subgoal_offset=offset))


def test_the_tcp_path_starts_at_zero_then_moves_the_subgoal_and_bad_tcp_is_refused():
    torch.manual_seed(0)
    grounding = InstructionGrounding(16, 2, tcp_dim=TCP_FEATURE_DIM)
    words, mask, image = torch.randn(2, 5, 16), torch.ones(2, 5, dtype=torch.bool), torch.randn(2, 8, 16)
    tcp = torch.randn(2, TCP_FEATURE_DIM)
    _, subgoal = grounding(words, mask, image, tcp)
    assert torch.equal(grounding.tcp_skip(tcp), torch.zeros(2, 3))
    torch.nn.init.eye_(grounding.tcp_skip.weight)  # the linear path: the sub-goal moves with the tcp
    _, moved = grounding(words, mask, image, tcp)
    torch.testing.assert_close(moved - subgoal, tcp[:, :3])
    with pytest.raises(ValueError, match=r"tcp must be \(2, 9\).*grounding_reads_tcp"):
        grounding(words, mask, image)
    with pytest.raises(ValueError, match=r"tcp must be \(2, 9\)"):
        grounding(words, mask, image, tcp[:, :3])
    with pytest.raises(ValueError, match="built without tcp_dim"):
        InstructionGrounding(16, 2)(words, mask, image, tcp)


def test_the_model_needs_the_state_for_its_subgoal_and_the_bind_loss_trains_the_tcp_path():
    model = TriVLA(_config(True)).eval()
    obs = example_observation()
    torch.nn.init.normal_(model.policy.grounding.tcp_skip.weight)
    with pytest.raises(ValueError, match="state is required.*grounding_reads_tcp"):
        model.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"])
    here = model.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    moved = obs["state"].copy()
    moved[0] += 0.5  # joint 1 turns the arm: the tcp moves
    assert not np.allclose(here, model.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], moved))
    q_vl, q_s = model.encode_vision_language(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=0)
    with pytest.raises(ValueError, match="state is required.*grounding_reads_tcp"):
        model.sample_actions(q_vl, q_s, features, seed=0)
    np.testing.assert_array_equal(model.sample_actions(q_vl, q_s, features, seed=0, state=obs["state"]),
                                  model.predict_action_chunk(obs, seed=0))

    batch = {"static_rgb": np.stack([obs["static_rgb"]] * 2), "wrist_rgb": np.stack([obs["wrist_rgb"]] * 2),
             "instruction": ["lift the red block", "lift the blue block"],
             "subgoal_position": torch.tensor([[0.5, 0.1, 0.03], [0.4, -0.2, 0.03]])}
    with pytest.raises(ValueError, match="missing 'state'.*grounding_reads_tcp"):
        model.compute_grounding_loss(batch)
    loss, _ = model.compute_grounding_loss({**batch, "state": torch.zeros(2, model.config.policy.state_dim)})
    loss.backward()
    assert model.policy.grounding.tcp_skip.weight.grad.abs().sum() > 0
    assert {"grounding.tcp_skip.weight", "grounding.subgoal_head.0.weight"} <= set(model.policy.binding_parameters())


def test_a_run_adds_the_tcp_path_to_a_grounding_keeping_its_attention():
    grounded = TriVLA(_config(False))
    rebuilt = apply_ablations(grounded, True, True, "--init", grounding_reads_tcp=True)
    assert rebuilt.config.policy.grounding_reads_tcp and rebuilt.policy.grounding.tcp_skip is not None
    for name, p in grounded.policy.grounding.named_parameters():
        if not name.startswith("subgoal_head.0."):
            assert torch.equal(p, rebuilt.policy.grounding.get_parameter(name)), name
    widths = (rebuilt.policy.grounding.subgoal_head[0].in_features, grounded.policy.grounding.subgoal_head[0].in_features)
    assert widths[0] == widths[1] + TCP_FEATURE_DIM
    assert apply_ablations(rebuilt, True, True, "--init") is rebuilt  # kept once there


def test_reading_the_tcp_without_grounding_or_tcp_features_is_refused_naming_the_field(tmp_path):
    config = make_config("tiny")
    with pytest.raises(ValueError, match="policy.grounding_reads_tcp.*instruction_grounding and policy.tcp_features"):
        dataclasses.replace(config, policy=dataclasses.replace(config.policy, grounding_reads_tcp=True))
    for options in ({}, {"grounding_weight": 1.0, "tcp_features": False}, {"stage": "video"}):
        settings = {"stage": "policy", "data": str(tmp_path), "out": str(tmp_path / "o"),
                    "grounding_reads_tcp": True, **options}
        with pytest.raises(ValueError, match=r"grounding_reads_tcp \(--grounding-reads-tcp\)"):
            TrainConfig(**settings).resolved().validate()
