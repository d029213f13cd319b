"""Rendered grounding scenes (train/grounding_scenes.py), the inverse kinematics that places the arm
along the oracle's approach (robot/panda_ik.py), and the re-fit of the grounding's read-out on them
(train/grounding_refit.py): labels are the plan's grasp, the arm is where it was asked to be, the set
is written atomically and never overwritten by other settings, and the re-fit trains the read-out alone."""

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.robot.panda_ik import solve_ik
from trivla_drake.robot.panda_kinematics import PandaKinematics
from trivla_drake.tasks.scene import HOME_ARM_Q, Layout, scene_from_spec
from trivla_drake.train import grounding_refit as refit
from trivla_drake.train import grounding_scenes as gs


def test_inverse_kinematics_reaches_a_reachable_pose_and_names_a_bad_target():
    kinematics = PandaKinematics()
    goal_q = np.asarray(HOME_ARM_Q) + np.array([0.3, -0.2, 0.1, 0.25, -0.1, 0.2, 0.3])
    target = kinematics.ee_pose(goal_q)
    q, position_error, rotation_error = solve_ik(kinematics, target, HOME_ARM_Q)
    assert position_error < 5e-4 and rotation_error < 5e-3
    np.testing.assert_allclose(kinematics.ee_pose(q)[:3, 3], target[:3, 3], atol=5e-4)
    assert np.all(q >= kinematics.q_lower) and np.all(q <= kinematics.q_upper)
    far = target.copy()
    far[:3, 3] = [3.0, 0.0, 0.5]  # out of reach: the error says so
    assert solve_ik(kinematics, far, HOME_ARM_Q, iterations=30)[1] > 1.0
    with pytest.raises(ValueError, match="target must be a finite 4x4 pose"):
        solve_ik(kinematics, np.eye(3), HOME_ARM_Q)


def test_a_point_on_the_path_is_measured_by_length_and_turns_in_proportion():
    a, b, c = np.eye(4), np.eye(4), np.eye(4)
    b[:3, 3] = [0.3, 0.0, 0.0]
    c[:3, 3] = [0.3, 0.1, 0.0]
    c[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # a quarter turn about z
    np.testing.assert_allclose(gs.point_on_path([a, b, c], 0.0), a, atol=1e-12)
    np.testing.assert_allclose(gs.point_on_path([a, b, c], 1.0), c, atol=1e-12)
    middle = gs.point_on_path([a, b, c], 0.875)  # 0.35 of 0.4 m: half-way along the second leg
    np.testing.assert_allclose(middle[:3, 3], [0.3, 0.05, 0.0], atol=1e-12)
    assert np.degrees(np.arctan2(middle[1, 0], middle[0, 0])) == pytest.approx(45.0)
    with pytest.raises(ValueError, match="fraction in"):
        gs.point_on_path([a, b], 1.5)


def test_scenes_are_labelled_with_the_plans_grasp_and_placed_along_its_approach():
    from trivla_drake.action import GRIPPER_CLOSE
    from trivla_drake.tasks.suite import get_task

    layout, kinematics = Layout.default(), PandaKinematics()
    scenes = [gs.sample_grounding_scene(i, 5, layout, kinematics) for i in range(4)]
    assert [s["task"] for s in scenes] == ["lift_block", "lift_block", "place_in_bowl", "place_in_bowl"]
    assert [s["along_approach"] for s in scenes] == [False, True, False, True]
    for scene in scenes:
        task = get_task(scene["task"])
        assert any(word in scene["instruction"] for word in ("red", "green", "blue")), scene["instruction"]
        assert task.name in gs.GROUNDING_SCENE_TASKS
        assert scene["state"].shape == (18,) and np.all(scene["state"][7:9] == gs.FINGER_OPEN)
        np.testing.assert_array_equal(scene["state"][:7], np.asarray(scene["spec"].arm_q, dtype=np.float32))
        assert np.all(scene["state"][9:] == 0)
        assert scene["subgoal_yaw"].shape == (2,) and np.linalg.norm(scene["subgoal_yaw"]) == pytest.approx(1.0, abs=1e-5)
    start, along = scenes[0], scenes[1]
    np.testing.assert_allclose(start["spec"].arm_q, gs.sample_grounding_scene(0, 5, layout, kinematics)["spec"].arm_q)
    # The label: where the oracle's plan for this scene first closes, raised by the tracking lag.
    from trivla_drake.tasks.suite import sample_task_instance

    spec, instance = sample_task_instance(get_task("lift_block"), np.random.default_rng([5, 0]), layout)
    plan = get_task("lift_block").plan(instance.params, scene_from_spec(spec, layout))
    close = next(wp for wp in plan if wp.gripper == GRIPPER_CLOSE)
    np.testing.assert_allclose(start["subgoal_position"], close.pose[:3, 3] + gs.CLOSE_TRACKING_LAG, atol=1e-6)
    # Along the approach: the tcp is moved off the start, never below the grasp.
    tcp = kinematics.ee_pose(np.asarray(along["spec"].arm_q))[:3, 3]
    assert tcp[2] >= along["subgoal_position"][2] - gs.CLOSE_TRACKING_LAG[2] - gs.IK_TOLERANCE
    start_tcp = kinematics.ee_pose(np.asarray(HOME_ARM_Q))[:3, 3]
    assert np.linalg.norm(tcp - start_tcp) > 0.02


def test_a_set_is_rendered_once_read_back_and_never_overwritten_by_other_settings(tmp_path):
    settings = gs.grounding_scene_settings(scenes=2, seed=3, image_size=32)
    folder = gs.ensure_grounding_scenes(tmp_path / "scenes", settings, progress=False)
    scenes = gs.GroundingScenes(folder)
    assert len(scenes) == 2 and scenes.static.shape == (2, 32, 32, 3) and scenes.wrist.shape == (2, 32, 32, 3)
    assert scenes.static.std() > 0 and scenes.state.shape == (2, 18) and scenes.subgoal_position.shape == (2, 3)
    assert scenes.along_approach.tolist() == [False, True]
    assert not any(p.name.startswith(".tmp") for p in tmp_path.iterdir())
    before = (folder / "static.npy").read_bytes()
    assert gs.ensure_grounding_scenes(folder, settings, progress=False) == folder  # reused as it is
    with pytest.raises(ValueError, match="other settings .*scenes: 2 there, 3 asked"):
        gs.ensure_grounding_scenes(folder, {**settings, "scenes": 3}, progress=False)
    assert (folder / "static.npy").read_bytes() == before
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty and does not hold grounding scenes"):
        gs.ensure_grounding_scenes(tmp_path / "other", settings, progress=False)
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "meta.json").write_text(json.dumps({**meta, "format": 0}))
    with pytest.raises(ValueError, match="format 0"):
        gs.GroundingScenes(folder)
    with pytest.raises(ValueError, match="scenes must be >= 1"):
        gs.grounding_scene_settings(scenes=0, seed=0, image_size=32)


def test_a_crash_while_rendering_leaves_no_partial_set(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("renderer died")

    monkeypatch.setattr(gs, "sample_grounding_scene", broken)
    with pytest.raises(RuntimeError, match="renderer died"):
        gs.ensure_grounding_scenes(tmp_path / "scenes", gs.grounding_scene_settings(scenes=2, seed=0, image_size=32),
                                   progress=False)
    assert list(tmp_path.iterdir()) == []


def _grounded_model():
    config = make_config("tiny", init_seed=4)
    config = dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, grounding_reads_gripper=True))
    model = TriVLA(config).eval()
    with torch.no_grad():  # the goal projection as a trained one would be, not at its zero start
        last = model.policy.grounding.goal[2]
        last.weight.copy_(0.1 * torch.randn(last.weight.shape, generator=torch.Generator().manual_seed(5)))
    return model


def test_the_refit_trains_the_grounding_readout_alone_and_lowers_its_loss():
    model = _grounded_model()
    rng = np.random.default_rng(0)

    def samples(n, words):
        state = np.zeros((n, 18), dtype=np.float32)
        state[:, :7], state[:, 7:9] = HOME_ARM_Q, gs.FINGER_OPEN
        views = rng.integers(0, 255, size=(2, n, model.image_size, model.image_size, 3), dtype=np.uint8)
        rendered = SimpleNamespace(  # what scene_samples reads of a GroundingScenes
            folder="memory", static=views[0], wrist=views[1], instructions=[words] * n, tasks=["lift_block"] * n,
            state=state, subgoal_position=(np.array([0.5, 0.0, 0.03]) + 0.05 * rng.normal(size=(n, 3))).astype(np.float32))
        return refit.scene_samples(model, rendered, progress=False)

    scenes, frames = samples(24, "lift the red block"), samples(16, "put the blue block in the bowl please")
    assert scenes.q_vl.dtype == torch.float16 and scenes.q_vl.shape[1] != frames.q_vl.shape[1]
    before = {k: v.clone() for k, v in model.state_dict().items()}
    readout = {f"policy.{name}" for name in refit.readout_parameters(model)}
    assert readout and not any(".goal." in name for name in readout)
    error_before = refit.subgoal_errors(model, scenes).mean()
    curve = refit.refit_readout(model, scenes, frames, steps=60, lr=3e-3, batch_size=8, log_every=20, progress=False)
    assert [step for step, _ in curve] == [20, 40, 60]
    assert curve[-1][1] < curve[0][1]
    assert refit.subgoal_errors(model, scenes).mean() < error_before
    changed = {k for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and changed <= readout  # the DiT, the Q_vl path and the goal projection are as they were
    assert not any(p.requires_grad for p in model.parameters())
    with pytest.raises(ValueError, match="scene_share must be in"):
        refit.refit_readout(model, scenes, frames, steps=1, lr=1e-3, scene_share=1.0)


def _scene_samples(model, n: int = 24):
    """Samples of `n` random views asking to lift the red block, labelled around one point."""
    rng = np.random.default_rng(1)
    state = np.zeros((n, 18), dtype=np.float32)
    state[:, :7], state[:, 7:9] = HOME_ARM_Q, gs.FINGER_OPEN
    views = rng.integers(0, 255, size=(2, n, model.image_size, model.image_size, 3), dtype=np.uint8)
    position = np.array([0.5, 0.0, 0.03]) + 0.03 * rng.normal(size=(n, 3))
    return refit.scene_samples(model, SimpleNamespace(
        folder="memory", static=views[0], wrist=views[1], instructions=["lift the red block"] * n,
        tasks=["lift_block"] * n, state=state, subgoal_position=position.astype(np.float32)),
        progress=False)


def test_the_groundings_outputs_are_the_goal_token_the_dit_reads_and_the_subgoal():
    model = _grounded_model()
    scenes = _scene_samples(model, n=6)
    goals, subgoals = refit.grounding_outputs(model, scenes, batch_size=4)
    assert goals.shape == (6, model.config.policy.hidden_size) and subgoals.shape[0] == 6
    torch.testing.assert_close(subgoals, refit.raw_subgoals(model, scenes))
    b = scenes.batch(torch.arange(6), scenes.q_vl.shape[1])
    with torch.no_grad():
        torch.testing.assert_close(subgoals, model.subgoal_of_features(b["q_vl"], b["q_vl_mask"], b["state"]).float())


def test_saved_samples_load_back_and_a_broken_file_is_named(tmp_path):
    model = _grounded_model()
    scenes = _scene_samples(model, n=4)
    refit.save_samples(scenes, tmp_path / "q" / "scenes.pt")
    assert [p.name for p in (tmp_path / "q").iterdir()] == ["scenes.pt"]  # no partial file left
    loaded = refit.load_samples(tmp_path / "q" / "scenes.pt")
    for name in ("q_vl", "q_vl_mask", "state", "subgoal_position"):
        assert torch.equal(getattr(loaded, name), getattr(scenes, name)), name
    assert loaded.tasks == scenes.tasks
    data = (tmp_path / "q" / "scenes.pt").read_bytes()
    (tmp_path / "q" / "scenes.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="scenes.pt holds no saved grounding samples"):
        refit.load_samples(tmp_path / "q" / "scenes.pt")
    torch.save({"format": 7}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt holds no saved grounding samples of format 1"):
        refit.load_samples(tmp_path / "other.pt")


def test_dataset_samples_are_the_grounding_frames_with_their_labels(tmp_path):
    from trivla_drake.data.lerobot_reader import LeRobotReader
    from trivla_drake.data.samples import TrainingSamples
    from trivla_drake.train.synthetic import write_synthetic_dataset

    model = _grounded_model()
    reader = LeRobotReader(write_synthetic_dataset(tmp_path / "d", episodes=2, length=10, image_size=16, tcp_pose=True))
    cameras = dict(static_camera=reader.camera_keys[0], wrist_camera=reader.camera_keys[1])
    frames = refit.dataset_samples(model, reader, stride=2, progress=False, **cameras)
    plain = TrainingSamples(reader, history=1, future_frames=0, cameras=[])
    # The synthetic gripper closes at frame 5: frames 0..4 train the grounding; every 2nd is kept.
    assert len(frames) == 6 and frames.q_vl.dtype == torch.float16
    counts = frames.q_vl_mask.sum(1)  # one instruction per episode: its rows are equally long, padded past that
    assert len(set(counts[:3].tolist())) == 1 and len(set(counts[3:].tolist())) == 1
    assert bool(frames.q_vl_mask[counts.argmax()].all())
    np.testing.assert_allclose(frames.subgoal_position[1].numpy(), plain[2]["subgoal_position"])
    np.testing.assert_allclose(frames.state[4].numpy(), plain[10 + 2]["observation.state"][-1])
    with pytest.raises(ValueError, match="stride must be >= 1"):
        refit.dataset_samples(model, reader, stride=0, progress=False, **cameras)
    with pytest.raises(ValueError, match="has no 'observation.tcp_pose'"):
        refit.dataset_samples(model, LeRobotReader(write_synthetic_dataset(tmp_path / "e", episodes=1, length=6)),
                              stride=1, progress=False, **cameras)


