"""System 1's instruction grounding: sub-goal labels from demonstrations, a module that learns which
image token the instruction names, its place in the model and loss, and the errors it raises."""

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.data.samples import TrainingSamples
from trivla_drake.data.subgoals import approach_frames, carry_frames, next_gripper_event_positions
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.instruction_grounding import InstructionGrounding, grounding_loss
from trivla_drake.nn.panda_tcp import normalize_position
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.synthetic import write_synthetic_dataset


def test_subgoal_is_the_position_at_the_next_gripper_change_then_the_last_frame():
    gripper = np.array([-1, -1, -1, 1, 1, -1, -1], dtype=float)  # closes at frame 3, opens at frame 5
    tcp = np.arange(21, dtype=float).reshape(7, 3)
    labels = next_gripper_event_positions(gripper, tcp)
    assert labels.dtype == np.float32 and labels.shape == (7, 3)
    expected_frames = [3, 3, 3, 5, 5, 6, 6]
    np.testing.assert_array_equal(labels, tcp[expected_frames])
    # no change at all: every frame's sub-goal is where the episode ends (a push)
    np.testing.assert_array_equal(next_gripper_event_positions(np.ones(4), tcp[:4]), tcp[[3, 3, 3, 3]])
    assert next_gripper_event_positions(np.zeros(0), np.zeros((0, 3))).shape == (0, 3)


def test_approach_frames_are_those_before_the_first_gripper_change():
    np.testing.assert_array_equal(approach_frames(np.array([-1, -1, 1, 1, -1.0])), [True, True, False, False, False])
    assert approach_frames(np.ones(3)).all()  # a push: no change, every frame approaches
    with pytest.raises(ValueError, match="gripper must be"):
        approach_frames(np.ones((2, 2)))


def test_carry_frames_run_from_the_last_grasp_to_the_release():
    # open, a missed grasp (closed, opened again), the grasp, the carry, the release
    gripper = np.array([1, 1, -1, -1, 1, 1, -1, -1, -1, 1, 1.0])
    np.testing.assert_array_equal(np.flatnonzero(carry_frames(gripper)), [6, 7, 8])
    # their sub-goal is where the hand opens (frame 9)
    tcp = np.arange(11 * 3, dtype=np.float64).reshape(11, 3)
    np.testing.assert_allclose(next_gripper_event_positions(gripper, tcp)[6:9], np.repeat(tcp[9:10], 3, axis=0))
    assert not carry_frames(np.array([1, 1, -1, -1.0])).any()  # a lift: never released
    assert not carry_frames(np.ones(4)).any()  # a push: never closed
    with pytest.raises(ValueError, match=r"\(T,\)"):
        carry_frames(np.ones((2, 2)))


def test_training_samples_add_the_carry_frames_of_the_tasks_asked(tmp_path):
    from trivla_drake.data.lerobot_format import EPISODE_TASK_KEY
    from trivla_drake.data.lerobot_writer import LeRobotWriter
    from trivla_drake.train.synthetic import CAMERAS, synthetic_features

    n = 12
    gripper = np.where((np.arange(n) >= 4) & (np.arange(n) < 9), -1.0, 1.0)  # grasp at 4, release at 9
    writer = LeRobotWriter(tmp_path / "d", fps=36.0, features=synthetic_features(16, 36.0, tcp_pose=True))
    for task in ("stack_block", "lift_block"):
        action = np.zeros((n, 7), dtype=np.float32)
        action[:, 6] = gripper
        pose = np.zeros((n, 7), dtype=np.float32)
        pose[:, 0], pose[:, 3] = np.arange(n) / n, 1.0
        writer.add_episode({"observation.state": np.zeros((n, 18), dtype=np.float32), "action": action,
                            "observation.tcp_pose": pose}, f"a {task} instruction",
                           videos={key: np.zeros((n, 16, 16, 3), dtype=np.uint8) for key in CAMERAS},
                           extra={EPISODE_TASK_KEY: task})
    plain = TrainingSamples(tmp_path / "d", history=1, future_frames=0, cameras=[])
    carry = TrainingSamples(tmp_path / "d", history=1, future_frames=0, cameras=[],
                            grounding_carry_tasks=("stack_block",))
    np.testing.assert_array_equal(np.flatnonzero(plain.grounding_frames(0)), [0, 1, 2, 3])
    np.testing.assert_array_equal(np.flatnonzero(carry.grounding_frames(0)), [0, 1, 2, 3, 4, 5, 6, 7, 8])
    np.testing.assert_array_equal(carry.grounding_frames(1), plain.grounding_frames(1))  # lift is not asked
    assert carry[6]["subgoal_in_loss"] and not plain[6]["subgoal_in_loss"]
    np.testing.assert_allclose(carry[6]["subgoal_position"], [9 / n, 0, 0])  # the release


def test_grounding_loss_counts_only_the_rows_asked():
    position = torch.tensor([[0.6, -0.1, 0.05], [0.4, 0.1, 0.1]])
    predicted = normalize_position(position)
    predicted[1] += 1.0  # only the second row is wrong
    assert float(grounding_loss(predicted, position, torch.tensor([True, False]))) == 0.0
    assert float(grounding_loss(predicted, position, torch.tensor([False, True]))) > 0.9
    none = grounding_loss(predicted.requires_grad_(), position, torch.tensor([False, False]))
    assert float(none.detach()) == 0.0 and none.requires_grad  # still in the graph (DDP needs every gradient)


@pytest.mark.parametrize(
    "gripper, tcp, message",
    [
        (np.ones((3, 1)), np.zeros((3, 3)), "gripper must be"),
        (np.ones(3), np.zeros((4, 3)), "tcp_position"),
        (np.array([1.0, np.nan]), np.zeros((2, 3)), "finite"),
    ],
)
def test_subgoal_labels_reject_bad_input(gripper, tcp, message):
    with pytest.raises(ValueError, match=message):
        next_gripper_event_positions(gripper, tcp)


def test_training_samples_carry_subgoals_when_the_dataset_has_tcp_poses(tmp_path):
    with_pose = TrainingSamples(write_synthetic_dataset(tmp_path / "a", episodes=1, length=10, tcp_pose=True),
                                history=1, future_frames=0, cameras=[])
    # the synthetic gripper closes for the second half: frames 0..4 aim at frame 5, the rest at the end
    frames = [with_pose.reader.episode_frames(0)["observation.tcp_pose"][k, :3] for k in (5, 9)]
    np.testing.assert_allclose(with_pose[2]["subgoal_position"], frames[0])
    np.testing.assert_allclose(with_pose[7]["subgoal_position"], frames[1])
    assert with_pose[4]["subgoal_in_loss"] and not with_pose[5]["subgoal_in_loss"]
    without = TrainingSamples(write_synthetic_dataset(tmp_path / "b", episodes=1, length=10),
                              history=1, future_frames=0, cameras=[])
    assert "subgoal_position" not in without[2]


# Colour names spelt with two letters, as System 2's byte tokens spell words: 0 = "ab", 1 = "ba",
# 2 = "bb". The names of colours 0 and 1 hold the same letters; only their order tells them apart.
_SPELLING = ((0, 1), (1, 0), (1, 1))


def _scenes(n, tokens=16, dim=32, colours=3, seed=0, spelt=False):
    """Each colour k shows in one random image token as channel k (the token's position on a 4x4 grid
    is its only location cue, given by a fixed position embedding); the instruction names one colour
    by channel `colours + k` of one token or, `spelt`, by its two letters (channels `colours` and
    `colours + 1`) in tokens 1 and 2; the target is that colour's grid cell."""
    gen = torch.Generator().manual_seed(seed)
    position = torch.randn(tokens, dim, generator=gen)
    images = 0.1 * torch.randn(n, tokens, dim, generator=gen) + position
    instruction = 0.1 * torch.randn(n, 4, dim, generator=gen)
    named = torch.randint(0, colours, (n,), generator=gen)
    target = torch.zeros(n, 3)
    for i in range(n):
        cells = torch.randperm(tokens, generator=gen)[:colours]
        images[i, cells, torch.arange(colours)] += 3.0
        if spelt:
            for token, letter in enumerate(_SPELLING[int(named[i])], start=1):
                instruction[i, token, colours + letter] += 3.0
        else:
            instruction[i, 1, colours + named[i]] += 3.0
        row, col = divmod(int(cells[named[i]]), 4)
        target[i, :2] = torch.tensor([row, col], dtype=torch.float32) / 4
    return instruction, images, target


@pytest.mark.parametrize("spelt", [False, True])
def test_grounding_learns_which_token_the_instruction_names(spelt):
    """Two hops in one: the instruction picks a colour, the attention finds that colour's token, the
    head reads its position. After training, held-out scenes are located far better than by the mean,
    also when a colour's name is spelt over two tokens whose order matters (byte tokens)."""
    torch.manual_seed(0)
    instruction, images, target = _scenes(600, spelt=spelt)
    mask = torch.ones(instruction.shape[:2], dtype=torch.bool)
    grounding = InstructionGrounding(32, num_heads=4)
    optimizer = torch.optim.Adam(grounding.parameters(), lr=3e-3)
    for step in range(400):
        batch = torch.randint(0, 500, (64,))
        _, predicted = grounding(instruction[batch], mask[batch], images[batch])
        loss = torch.nn.functional.mse_loss(predicted, target[batch])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        goal, predicted = grounding(instruction[500:], mask[500:], images[500:])
    error = (predicted - target[500:])[:, :2].norm(dim=-1).mean()
    baseline = (target[500:] - target[:500].mean(0))[:, :2].norm(dim=-1).mean()
    assert goal.shape == (100, 32)
    assert error < 0.35 * baseline, (float(error), float(baseline))


def test_grounding_ignores_masked_instruction_tokens_and_starts_with_a_zero_goal():
    instruction, images, _ = _scenes(4)
    grounding = InstructionGrounding(32, num_heads=2)
    mask = torch.tensor([[True, True, False, False]]).expand(4, -1)
    junk = instruction.clone()
    junk[:, 2:] = 100.0
    goal, a = grounding(instruction, mask, images)
    _, b = grounding(junk, mask, images)
    torch.testing.assert_close(a, b)
    assert torch.equal(goal, torch.zeros_like(goal))  # zero-initialised: a new grounding changes nothing yet


def test_grounding_loss_is_in_tcp_feature_units():
    position = torch.tensor([[0.6, -0.1, 0.05]])
    predicted = normalize_position(position)
    assert float(grounding_loss(predicted, position)) == 0.0
    assert float(grounding_loss(predicted + 1.0, position)) > 0.9


def _grounded_model():
    config = make_config("tiny")
    return TriVLA(dataclasses.replace(config, policy=dataclasses.replace(config.policy, instruction_grounding=True)))


def _batch(model):
    obs = example_observation()
    batch = {
        "static_rgb": np.stack([obs["static_rgb"]] * 2), "wrist_rgb": np.stack([obs["wrist_rgb"]] * 2),
        "instruction": ["lift the red block", "open the drawer"],
        "state": torch.zeros(2, model.config.policy.state_dim),
        "action": torch.zeros(2, model.config.policy.action_horizon, model.config.policy.action_dim),
        "subgoal_position": torch.tensor([[0.5, 0.1, 0.03], [0.4, -0.2, 0.2]]),
    }
    return batch


def test_compute_loss_adds_the_weighted_grounding_loss_and_trains_the_grounding():
    model = _grounded_model().eval()
    batch = _batch(model)
    loss, info = model.compute_loss(batch, generator=torch.Generator().manual_seed(0), grounding_weight=2.0)
    assert {"flow_loss", "grounding_loss"} <= set(info)
    assert abs(info["loss"] - info["flow_loss"] - 2.0 * info["grounding_loss"]) < 1e-5
    loss.backward()
    assert model.policy.grounding.query[1].weight.grad.abs().sum() > 0
    assert model.policy.grounding.subgoal_head[2].weight.grad.abs().sum() > 0
    # inference runs the grounding too: a chunk comes out for one observation
    chunk = model.predict_action_chunk(example_observation(), seed=0)
    assert chunk.shape == (model.config.policy.action_horizon, model.config.policy.action_dim)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda b: b.pop("subgoal_position"), "subgoal_position"),
        (lambda b: b.update(subgoal_position=torch.zeros(2, 2)), r"subgoal_position'\] must be finite \(2, 3\)"),
        (lambda b: b.update(subgoal_position=torch.full((2, 3), float("nan"))), "subgoal_position"),
        (lambda b: b.update(subgoal_in_loss=torch.ones(3, dtype=torch.bool)), r"subgoal_in_loss'\] must be \(2,\)"),
    ],
)
@pytest.mark.parametrize("alone", [False, True])
def test_compute_loss_names_a_missing_or_bad_subgoal(change, message, alone):
    model = _grounded_model().eval()
    batch = _batch(model)
    change(batch)
    with pytest.raises(ValueError, match=message):
        if alone:
            model.compute_grounding_loss(batch)
        else:
            model.compute_loss(batch, generator=torch.Generator().manual_seed(0))


def test_compute_grounding_loss_is_the_subgoal_loss_alone():
    """The bind phase's loss: the same sub-goal loss compute_loss adds, with no flow matching, and
    gradient only into the grounding and the Q_vl path; refused without a grounding."""
    model = _grounded_model().eval()
    batch = _batch(model)
    _, joint = model.compute_loss(batch, generator=torch.Generator().manual_seed(0))
    loss, info = model.compute_grounding_loss(batch)
    assert set(info) == {"grounding_loss", "loss"} and info["loss"] == pytest.approx(joint["grounding_loss"], rel=1e-5)
    loss.backward()
    with_grad = {name for name, p in model.policy.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    # the source embedding marks Q_vl against Q_p tokens for the DiT: bind leaves it as it is
    assert with_grad and with_grad - {"source_embed"} <= set(model.policy.binding_parameters())
    with pytest.raises(ValueError, match="no instruction grounding"):
        TriVLA(make_config("tiny")).compute_grounding_loss(batch)


def test_grounding_needs_system2():
    config = make_config("tiny")
    with pytest.raises(ValueError, match="policy.instruction_grounding.*use_system2"):
        dataclasses.replace(config, use_system2=False,
                            policy=dataclasses.replace(config.policy, instruction_grounding=True))
