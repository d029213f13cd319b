"""The instruction grounding that also reads how far the gripper is closed
(`PolicyConfig.grounding_reads_gripper`): a second read-out answers while a block is held, so one
instruction can name one block before the grasp and another after it. With no block held the grounding
is exactly the one it was; it needs the robot state wherever it runs, says so naming the field, a run
adds it to a grounded checkpoint as a copy of its read-out, and a held-only bind trains nothing else."""

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.config_io import with_flags
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.instruction_grounding import InstructionGrounding
from trivla_drake.nn.panda_gripper import MAX_GRIPPER_WIDTH, gripper_closure, holding_block
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.model_setup import apply_ablations

BLOCK_WIDTH = 0.045  # the suite's blocks [m]


def _config(reads_gripper: bool):
    config = make_config("tiny")
    return dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, grounding_reads_gripper=reads_gripper))


def _state(width: float) -> np.ndarray:
    state = example_observation()["state"].copy()
    state[7] = state[8] = width / 2
    return state


def test_closure_is_zero_open_one_shut_and_a_block_between_the_fingers_is_held():
    states = torch.zeros(4, 18)
    states[0, 7:9] = MAX_GRIPPER_WIDTH / 2
    states[1, 7:9] = BLOCK_WIDTH / 2
    states[3, 7:9] = 0.005  # a thin handle
    closure = gripper_closure(states)
    torch.testing.assert_close(closure, torch.tensor([[0.0], [0.4375], [1.0], [0.875]]))
    assert holding_block(closure).tolist() == [False, True, False, False]
    with pytest.raises(ValueError, match=r"state must be \(B, >= 9\)"):
        gripper_closure(torch.zeros(3, 7))


def test_the_held_readout_answers_only_while_a_block_is_held():
    torch.manual_seed(0)
    plain = InstructionGrounding(16, 2)
    reading = InstructionGrounding(16, 2, reads_gripper=True)
    reading.load_state_dict(plain.state_dict(), strict=False)
    words, mask, image = torch.randn(2, 5, 16), torch.ones(2, 5, dtype=torch.bool), torch.randn(2, 8, 16)
    open_, held = torch.zeros(2, 1), torch.full((2, 1), 0.44)
    reading.start_held_from_open()  # a copy: the same answers in both phases
    torch.testing.assert_close(reading(words, mask, image, gripper=held), plain(words, mask, image))
    torch.nn.init.normal_(reading.held["query"][1].weight)  # as if trained on the carrying frames
    torch.testing.assert_close(reading(words, mask, image, gripper=open_), plain(words, mask, image))
    assert not torch.allclose(reading(words, mask, image, gripper=held)[1], plain(words, mask, image)[1])
    mixed = reading(words, mask, image, gripper=torch.tensor([[0.0], [0.44]]))[1]
    torch.testing.assert_close(mixed[0], plain(words, mask, image)[1][0])
    torch.testing.assert_close(mixed[1], reading(words, mask, image, gripper=held)[1][1])
    with pytest.raises(ValueError, match=r"gripper must be \(2, 1\).*grounding_reads_gripper"):
        reading(words, mask, image)
    with pytest.raises(ValueError, match=r"gripper must be \(2, 1\)"):
        reading(words, mask, image, gripper=torch.zeros(2))
    with pytest.raises(ValueError, match="built without reads_gripper"):
        plain(words, mask, image, gripper=open_)
    with pytest.raises(ValueError, match="no held-block read-out"):
        plain.start_held_from_open()


def test_the_model_needs_the_state_for_its_subgoal_and_the_bind_loss_trains_the_held_readout():
    model = TriVLA(_config(True)).eval()
    obs = example_observation()
    views = obs["static_rgb"], obs["wrist_rgb"], obs["instruction"]
    with pytest.raises(ValueError, match="state is required.*grounding_reads_gripper"):
        model.predict_subgoal(*views)
    opened = model.predict_subgoal(*views, _state(MAX_GRIPPER_WIDTH))
    assert not np.allclose(opened, model.predict_subgoal(*views, _state(BLOCK_WIDTH)))  # two read-outs
    assert np.array_equal(opened, model.predict_subgoal(*views, _state(0.0)))  # closed on nothing: not held
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
    states = torch.from_numpy(np.stack([_state(MAX_GRIPPER_WIDTH), _state(BLOCK_WIDTH)])).float()
    loss, _ = model.compute_grounding_loss({**batch, "state": states})
    loss.backward()
    held = model.policy.held_parameters()
    assert held and all(p.grad is not None and p.grad.abs().sum() > 0 for p in held.values())
    assert set(held) <= set(model.policy.binding_parameters())  # a follow run keeps it


def test_a_run_adds_the_held_readout_as_a_copy_keeping_every_weight():
    grounded = TriVLA(_config(False))
    torch.nn.init.normal_(grounded.policy.grounding.score[1].weight)
    rebuilt = apply_ablations(grounded, True, True, "--init", grounding_reads_gripper=True)
    assert rebuilt.config.policy.grounding_reads_gripper and rebuilt.policy.grounding.held is not None
    for name, p in grounded.policy.named_parameters():
        assert torch.equal(p, rebuilt.policy.get_parameter(name)), name
    for name in ("query", "score", "subgoal_head"):
        for key, value in getattr(grounded.policy.grounding, name).state_dict().items():
            assert torch.equal(rebuilt.policy.grounding.held[name].state_dict()[key], value), (name, key)
    assert apply_ablations(rebuilt, True, True, "--init") is rebuilt  # kept once there


def test_reading_the_gripper_without_grounding_or_a_held_only_bind_without_it_is_refused(tmp_path):
    config = make_config("tiny")
    with pytest.raises(ValueError, match="policy.grounding_reads_gripper.*policy.instruction_grounding"):
        dataclasses.replace(config, policy=dataclasses.replace(config.policy, grounding_reads_gripper=True))
    base = TrainConfig(stage="policy", data=str(tmp_path), out=str(tmp_path / "o"))
    for stage in ("policy", "video"):
        with pytest.raises(ValueError, match=r"policy.grounding.reads_gripper"):
            with_flags(base, {"stage": stage, "policy.grounding.reads_gripper": True}).resolved().validate()
    held_only = with_flags(base, {"policy.grounding.weight": 1.0, "policy.grounding.phase": "bind", "init": str(tmp_path),
                                  "policy.grounding.keep": True, "policy.grounding.reads_gripper": True,
                                  "policy.grounding.bind_held_only": True})
    held_only.resolved().validate()
    for missing in ("keep", "reads_gripper"):
        with pytest.raises(ValueError, match=r"policy.grounding.bind_held_only .*policy.grounding.reads_gripper"):
            with_flags(held_only, {f"policy.grounding.{missing}": False}).resolved().validate()
