"""The instruction grounding that also reads how far the gripper is closed
(`PolicyConfig.grounding_reads_gripper`): one instruction can then name one block before the grasp and
another after it. With the fingers open the grounding is exactly the one it was (the path has no bias
and starts at zero); it needs the robot state wherever it runs, says so naming the field, and a run adds
it to a grounded checkpoint keeping every weight it had."""

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.config import make_config
from trivla_drake.nn.instruction_grounding import InstructionGrounding
from trivla_drake.nn.panda_gripper import MAX_GRIPPER_WIDTH, gripper_closure
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.trainer import apply_ablations


def _config(reads_gripper: bool):
    config = make_config("tiny")
    return dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, grounding_reads_gripper=reads_gripper))


def _state(width: float) -> np.ndarray:
    state = example_observation()["state"].copy()
    state[7] = state[8] = width / 2
    return state


def test_closure_is_zero_open_one_shut_and_a_bad_state_is_refused():
    states = torch.zeros(3, 18)
    states[0, 7:9] = MAX_GRIPPER_WIDTH / 2
    states[1, 7:9] = 0.0225  # a 4.5 cm block between the fingers
    torch.testing.assert_close(gripper_closure(states), torch.tensor([[0.0], [0.4375], [1.0]]))
    with pytest.raises(ValueError, match=r"state must be \(B, >= 9\)"):
        gripper_closure(torch.zeros(3, 7))


def test_open_fingers_leave_the_grounding_as_it_was_and_a_closed_gripper_moves_it():
    torch.manual_seed(0)
    plain = InstructionGrounding(16, 2)
    reading = InstructionGrounding(16, 2, reads_gripper=True)
    reading.load_state_dict(plain.state_dict(), strict=False)
    words, mask, image = torch.randn(2, 5, 16), torch.ones(2, 5, dtype=torch.bool), torch.randn(2, 8, 16)
    torch.nn.init.normal_(reading.gripper.weight)  # as if trained
    open_, held = torch.zeros(2, 1), torch.full((2, 1), 0.44)
    torch.testing.assert_close(reading(words, mask, image, gripper=open_), plain(words, mask, image))
    assert not torch.allclose(reading(words, mask, image, gripper=held)[1], plain(words, mask, image)[1])
    with pytest.raises(ValueError, match=r"gripper must be \(2, 1\).*grounding_reads_gripper"):
        reading(words, mask, image)
    with pytest.raises(ValueError, match=r"gripper must be \(2, 1\)"):
        reading(words, mask, image, gripper=torch.zeros(2))
    with pytest.raises(ValueError, match="built without reads_gripper"):
        plain(words, mask, image, gripper=open_)


def test_the_model_needs_the_state_for_its_subgoal_and_the_bind_loss_trains_the_gripper_path():
    model = TriVLA(_config(True)).eval()
    obs = example_observation()
    views = obs["static_rgb"], obs["wrist_rgb"], obs["instruction"]
    with pytest.raises(ValueError, match="state is required.*grounding_reads_gripper"):
        model.predict_subgoal(*views)
    opened = model.predict_subgoal(*views, _state(MAX_GRIPPER_WIDTH))
    assert np.array_equal(opened, model.predict_subgoal(*views, _state(0.045)))  # the path starts at zero
    torch.nn.init.normal_(model.policy.grounding.gripper.weight)
    assert np.array_equal(opened, model.predict_subgoal(*views, _state(MAX_GRIPPER_WIDTH)))
    assert not np.allclose(opened, model.predict_subgoal(*views, _state(0.045)))
    q_vl, q_s = model.encode_vision_language(*views, obs["state"])
    features = model.encode_dynamics(*views, seed=0)
    with pytest.raises(ValueError, match="state is required.*grounding_reads_gripper"):
        model.sample_actions(q_vl, q_s, features, seed=0)
    np.testing.assert_array_equal(model.sample_actions(q_vl, q_s, features, seed=0, state=obs["state"]),
                                  model.predict_action_chunk(obs, seed=0))

    batch = {"static_rgb": np.stack([obs["static_rgb"]] * 2), "wrist_rgb": np.stack([obs["wrist_rgb"]] * 2),
             "instruction": ["stack the red block on the blue block"] * 2,
             "subgoal_position": torch.tensor([[0.5, 0.1, 0.03], [0.4, -0.2, 0.08]])}
    with pytest.raises(ValueError, match="missing 'state'.*grounding_reads_gripper"):
        model.compute_grounding_loss(batch)
    states = torch.from_numpy(np.stack([_state(MAX_GRIPPER_WIDTH), _state(0.045)])).float()
    loss, _ = model.compute_grounding_loss({**batch, "state": states})
    loss.backward()
    assert model.policy.grounding.gripper.weight.grad.abs().sum() > 0
    assert "grounding.gripper.weight" in model.policy.binding_parameters()


def test_a_run_adds_the_gripper_path_to_a_grounding_keeping_every_weight():
    grounded = TriVLA(_config(False))
    rebuilt = apply_ablations(grounded, True, True, "--init", grounding_reads_gripper=True)
    assert rebuilt.config.policy.grounding_reads_gripper and rebuilt.policy.grounding.gripper is not None
    assert torch.equal(rebuilt.policy.grounding.gripper.weight, torch.zeros_like(rebuilt.policy.grounding.gripper.weight))
    for name, p in grounded.policy.named_parameters():
        assert torch.equal(p, rebuilt.policy.get_parameter(name)), name
    assert apply_ablations(rebuilt, True, True, "--init") is rebuilt  # kept once there


def test_reading_the_gripper_without_grounding_is_refused_naming_the_field(tmp_path):
    config = make_config("tiny")
    with pytest.raises(ValueError, match="policy.grounding_reads_gripper.*policy.instruction_grounding"):
        dataclasses.replace(config, policy=dataclasses.replace(config.policy, grounding_reads_gripper=True))
    for options in ({}, {"stage": "video"}):
        settings = {"stage": "policy", "data": str(tmp_path), "out": str(tmp_path / "o"),
                    "grounding_reads_gripper": True, **options}
        with pytest.raises(ValueError, match=r"grounding_reads_gripper \(--grounding-reads-gripper\)"):
            TrainConfig(**settings).resolved().validate()
