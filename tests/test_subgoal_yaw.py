"""The grounding's yaw (`PolicyConfig.subgoal_yaw`): its labels are the hand's yaw at the next gripper
event modulo a quarter turn, System 1 reads it as a turn from the hand's own yaw, a bind run adds it to
a grounding keeping everything else, and every way to use it wrongly is refused naming the field."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from pydrake.math import RotationMatrix

from trivla_drake.data.subgoals import next_gripper_event_yaws, quarter_turn_yaw_features, quaternion_yaw
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.config import make_config
from trivla_drake.nn.instruction_grounding import InstructionGrounding, grounding_loss
from trivla_drake.nn.panda_tcp import PandaTcpFeatures
from trivla_drake.nn.policy import quarter_turn_to
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.tasks.scene import hand_down
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.trainer import apply_ablations


def _quaternion(yaw: float) -> np.ndarray:
    q = RotationMatrix(hand_down(yaw)).ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z()])


def _config(yaw: bool):
    config = make_config("tiny")
    return dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, subgoal_offset=True, subgoal_yaw=yaw))


def test_the_yaw_features_are_the_hand_yaw_modulo_a_quarter_turn():
    for yaw in (-1.2, -0.3, 0.0, 0.5, 1.4):
        assert quaternion_yaw(_quaternion(yaw)) == pytest.approx(yaw)
        np.testing.assert_allclose(quarter_turn_yaw_features(_quaternion(yaw)),
                                   [math.cos(4 * yaw), math.sin(4 * yaw)], atol=1e-6)
        # A quarter turn closes on the same faces; an eighth turn is the worst grasp, the opposite.
        np.testing.assert_allclose(quarter_turn_yaw_features(_quaternion(yaw + math.pi / 2)),
                                   quarter_turn_yaw_features(_quaternion(yaw)), atol=1e-6)
        np.testing.assert_allclose(quarter_turn_yaw_features(_quaternion(yaw + math.pi / 4)),
                                   -quarter_turn_yaw_features(_quaternion(yaw)), atol=1e-6)
    with pytest.raises(ValueError, match="tcp_quaternion must be"):
        quarter_turn_yaw_features(np.zeros(3))


def test_the_labels_take_the_yaw_where_the_gripper_next_changes():
    gripper = np.array([1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
    yaws = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    labels = next_gripper_event_yaws(gripper, np.stack([_quaternion(y) for y in yaws]))
    expected = [0.3, 0.3, 0.3, 0.5, 0.5, 0.5]  # frames 0-2: the close at 3; then the open at 5; then the end
    np.testing.assert_allclose(labels, [[math.cos(4 * y), math.sin(4 * y)] for y in expected], atol=1e-6)
    with pytest.raises(ValueError, match=r"tcp_quaternion \(T, 4\)"):
        next_gripper_event_yaws(gripper, np.zeros((6, 3)))
    with pytest.raises(ValueError, match="must be finite"):
        next_gripper_event_yaws(gripper, np.full((6, 4), np.nan))
    assert next_gripper_event_yaws(np.zeros(0), np.zeros((0, 4))).shape == (0, 2)


def test_the_turn_is_zero_when_the_hand_already_has_the_yaw():
    tcp_features = PandaTcpFeatures()
    state = torch.tensor(example_observation()["state"], dtype=torch.float32)[None]
    tcp = tcp_features(state)
    hand = math.atan2(float(tcp[0, 4]), float(tcp[0, 3]))
    for offset in (0.0, 0.3, -0.6, math.pi / 2):
        psi = hand + offset
        turn = quarter_turn_to(torch.tensor([[math.cos(4 * psi), math.sin(4 * psi)]]), tcp)
        torch.testing.assert_close(turn, torch.tensor([[math.cos(4 * offset), math.sin(4 * offset)]]),
                                   atol=1e-5, rtol=0)


def test_the_yaw_head_leaves_the_goal_as_it_was_and_its_loss_needs_the_labels():
    torch.manual_seed(0)
    plain = InstructionGrounding(16, 2)
    with_yaw = InstructionGrounding(16, 2, yaw_tokens=8)
    with_yaw.load_state_dict(plain.state_dict(), strict=False)
    words, mask, image = torch.randn(2, 5, 16), torch.ones(2, 5, dtype=torch.bool), torch.randn(2, 8, 16)
    goal, subgoal = plain(words, mask, image)
    goal_yaw, subgoal_yaw = with_yaw(words, mask, image)
    torch.testing.assert_close(goal_yaw, goal)
    torch.testing.assert_close(subgoal_yaw[:, :3], subgoal)
    assert subgoal_yaw.shape == (2, 5)
    with pytest.raises(ValueError, match=r"image_tokens must be \(B, 8, D\) for the yaw read-out"):
        with_yaw(words, mask, image[:, :6])
    position = torch.tensor([[0.5, 0.1, 0.03], [0.4, -0.2, 0.03]])
    with pytest.raises(ValueError, match="subgoal_yaw is required"):
        grounding_loss(subgoal_yaw, position)
    labels = subgoal_yaw[:, 3:].detach()
    torch.testing.assert_close(grounding_loss(subgoal_yaw, position, subgoal_yaw=labels),
                               grounding_loss(subgoal, position))
    assert grounding_loss(subgoal_yaw, position, subgoal_yaw=-labels) > grounding_loss(subgoal, position)


def test_the_model_trains_and_predicts_the_yaw_and_reads_it_in_system1():
    model = TriVLA(_config(True)).eval()
    obs = example_observation()
    yaw = model.predict_subgoal_yaw(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    assert -math.pi / 4 < yaw <= math.pi / 4
    position, same_yaw = model.predict_grounding(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    assert same_yaw == yaw and position.shape == (3,)
    assert model.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"]).shape == (3,)
    with pytest.raises(ValueError, match="predicts no yaw"):
        TriVLA(_config(False)).predict_subgoal_yaw(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"])

    batch = {"static_rgb": np.stack([obs["static_rgb"]] * 2), "wrist_rgb": np.stack([obs["wrist_rgb"]] * 2),
             "instruction": ["lift the red block", "lift the blue block"],
             "subgoal_position": torch.tensor([[0.5, 0.1, 0.03], [0.4, -0.2, 0.03]])}
    with pytest.raises(ValueError, match="missing 'subgoal_yaw'"):
        model.compute_grounding_loss(batch)
    with pytest.raises(ValueError, match=r"subgoal_yaw'\] must be finite \(2, 2\)"):
        model.compute_grounding_loss({**batch, "subgoal_yaw": torch.zeros(2, 3)})
    loss, _ = model.compute_grounding_loss({**batch, "subgoal_yaw": torch.tensor([[1.0, 0.0], [1.0, 0.0]])})
    loss.backward()
    assert model.policy.grounding.yaw_head.weight.grad.abs().sum() > 0
    assert {"grounding.yaw_head.weight", "grounding.yaw_project.1.weight"} <= set(model.policy.binding_parameters())

    # System 1 starts as without the yaw (its encoder's output at zero), then reads it. AdaLN-Zero: a new
    # DiT's gates are closed, so Q_s reaches no action token until they are opened.
    for block in model.policy.dit.blocks:
        torch.nn.init.normal_(block.modulation[1].weight, std=0.5)
    q_vl, q_s = model.encode_vision_language(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=0)
    before = model.sample_actions(q_vl, q_s, features, seed=0, state=obs["state"])
    assert torch.equal(model.policy.subgoal_yaw(torch.randn(1, 2), torch.randn(1, 9)), torch.zeros(1, 32))
    with pytest.raises(ValueError, match="state is required.*subgoal_yaw"):
        model.sample_actions(q_vl, q_s, features, seed=0)
    model.policy.subgoal_yaw.mlp[2].weight.data.normal_()
    assert not np.allclose(before, model.sample_actions(q_vl, q_s, features, seed=0, state=obs["state"]))


def test_a_run_adds_the_yaw_to_a_grounding_keeping_the_rest():
    grounded = TriVLA(_config(False))
    rebuilt = apply_ablations(grounded, True, True, "--init", subgoal_offset=True, subgoal_yaw=True)
    assert rebuilt.config.policy.subgoal_yaw and rebuilt.policy.grounding.yaw_head is not None
    kept = grounded.policy.state_dict()
    for name, tensor in rebuilt.policy.state_dict().items():
        if name in kept:
            assert torch.equal(tensor, kept[name]), name
        else:
            assert name.startswith(("grounding.yaw_head.", "grounding.yaw_project.", "subgoal_yaw.")), name
    assert apply_ablations(rebuilt, True, True, "--init") is rebuilt  # kept once there


def test_the_yaw_without_grounding_or_tcp_features_is_refused_naming_the_field(tmp_path):
    config = make_config("tiny")
    with pytest.raises(ValueError, match="policy.subgoal_yaw.*instruction_grounding and policy.tcp_features"):
        dataclasses.replace(config, policy=dataclasses.replace(config.policy, subgoal_yaw=True))
    for options in ({}, {"grounding_weight": 1.0, "tcp_features": False}, {"stage": "video"}):
        settings = {"stage": "policy", "data": str(tmp_path), "out": str(tmp_path / "o"),
                    "subgoal_yaw": True, **options}
        with pytest.raises(ValueError, match=r"subgoal_yaw \(--subgoal-yaw\)"):
            TrainConfig(**settings).resolved().validate()


def test_the_grounding_check_reports_the_yaw_along_the_approach():
    from trivla_drake.eval.grounding_check import format_grounding_check, grounding_check

    check = grounding_check(TriVLA(_config(True)).eval(), scenes=1)
    assert check.driver == "oracle" and set(check.approach_yaw) == {"far", "mid", "near"}
    for band, row in check.approach_yaw.items():  # one yaw query per query of the block approached
        assert row["queries"] == check.approach[band]["approached"]["queries"]
        assert 0 <= row["within_tolerance"] <= row["queries"]
        # split by the hand's own yaw: the two parts add up
        assert row["hand_right"][1] + row["hand_off"][1] == row["queries"]
        assert row["hand_right"][0] + row["hand_off"][0] == row["within_tolerance"]
    # the oracle turns its hand to the block's faces before it comes near
    assert check.approach_yaw["near"]["hand_off"][1] == 0
    assert 0 <= check.approach_yaw["near"]["median_error_deg"] <= 45
    text = format_grounding_check(check)
    assert "along the oracle's approach" in text and "its yaw along the approach" in text and "hand off 0/" in text
    plain = grounding_check(TriVLA(_config(False)).eval(), scenes=1, approach=False)
    assert plain.approach_yaw is None and "yaw" not in format_grounding_check(plain)


def test_the_grounding_check_can_follow_a_learned_policy_chunk_by_chunk():
    from trivla_drake.eval.grounding_check import grounding_check
    from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy

    model = TriVLA(_config(True)).eval()

    class Counting(TriVLAHarnessPolicy):
        calls = 0

        def act(self, observation):
            Counting.calls += 1
            return super().act(observation)

    check = grounding_check(model, scenes=1, driver=Counting(model, name="counted"))
    assert check.driver == "counted"
    asked = sum(band["approached"]["queries"] for band in check.approach.values())
    assert 1 <= asked <= Counting.calls  # once per chunk until the gripper first closes
    assert sum(band["queries"] for band in check.approach_yaw.values()) == asked


def test_drive_needs_grounding_scenes(capsys):
    from trivla_drake.cli import main

    assert main(["probe", "--drive", "oracle"]) == 2
    assert "--drive chooses whose trajectories --grounding-scenes follows" in capsys.readouterr().err
