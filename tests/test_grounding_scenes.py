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

from trivla_drake.nn.config import make_config
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


def test_a_prelude_leaves_the_scene_as_the_oracle_would():
    from trivla_drake.tasks.scene import sample_scene
    from trivla_drake.tasks.suite import TaskInstance, get_task

    layout = Layout.default()

    def applied(name, spec, params=()):
        instance = TaskInstance(name, params, "")
        plan = get_task(name).plan(params, scene_from_spec(spec, layout))
        return gs.after_prelude(spec, instance, plan, layout)

    closed = sample_scene(np.random.default_rng(1), layout, drawer_open=False, lamp_on=False)
    assert applied("open_drawer", closed).drawer_opening == pytest.approx(0.13)
    assert applied("close_drawer", applied("open_drawer", closed)).drawer_opening == 0.0
    assert applied("turn_on_light", closed).lamp_on and not applied("turn_off_light", closed).lamp_on
    for name in ("place_in_bowl", "push_block_left", "rotate_block_right", "stack_block", "unstack_block"):
        rng = np.random.default_rng(7)
        task = get_task(name)
        drawn = (sample_scene(rng, layout, stack=name == "unstack_block") for _ in range(50))
        spec = next(s for s in drawn if task.candidates(scene_from_spec(s, layout)))
        params = task.candidates(scene_from_spec(spec, layout))[0]
        before, after = scene_from_spec(spec, layout), scene_from_spec(applied(name, spec, params), layout)
        assert task.success(params, before, after), name  # the task's own test says it was done
        others = [c for c in spec.blocks if c != params[0]]
        assert all(np.allclose(after.block_position(c), before.block_position(c)) for c in others), name
    with pytest.raises(ValueError, match="no prelude effect is known for task 'lift_block'"):
        applied("lift_block", closed, ("red",))


def test_chain_start_scenes_start_where_a_prelude_left_the_arm_and_keep_their_task_possible():
    from trivla_drake.action import GRIPPER_CLOSE
    from trivla_drake.tasks.suite import get_task

    layout, kinematics = Layout.default(), PandaKinematics()
    assert "chain_starts" not in gs.grounding_scene_settings(scenes=2, seed=0, image_size=32)
    assert gs.grounding_scene_settings(scenes=2, seed=0, image_size=32, chain_starts=0.5)["chain_starts"] == 0.5
    with pytest.raises(ValueError, match="chain_starts must be a fraction"):
        gs.grounding_scene_settings(scenes=2, seed=0, image_size=32, chain_starts=1.5)
    # Without chain starts a scene is drawn as before they existed.
    plain = gs.sample_grounding_scene(3, 5, layout, kinematics)
    np.testing.assert_array_equal(gs.sample_grounding_scene(3, 5, layout, kinematics, 0.0)["state"], plain["state"])
    assert not plain["chain_start"]
    home_tcp = kinematics.ee_pose(np.asarray(HOME_ARM_Q))[:3, 3]
    for index in range(6):
        scene = gs.sample_grounding_scene(index, 5, layout, kinematics, 1.0)
        assert scene["chain_start"] and scene["along_approach"] == (index % 2 == 1)
        task, state = get_task(scene["task"]), scene_from_spec(scene["spec"], layout)
        possible = task.candidates(state)
        assert possible, scene["instruction"]
        # The label is the plan's grasp in the scene as the preludes left it.
        closes = {tuple(np.round(next(wp for wp in task.plan(p, state) if wp.gripper == GRIPPER_CLOSE).pose[:3, 3]
                                 + gs.CLOSE_TRACKING_LAG, 5)) for p in possible}
        assert tuple(np.round(scene["subgoal_position"].astype(float), 5)) in closes
        tcp = kinematics.ee_pose(np.asarray(scene["spec"].arm_q))[:3, 3]
        assert np.linalg.norm(tcp - home_tcp) > 0.05  # not the start posture: a prelude's end or the way on


def test_stacked_pick_scenes_name_the_top_block_of_a_stack_and_are_labelled_at_its_height():
    from trivla_drake.tasks.suite import BLOCK_SIZE, STACKED_PICK_TASKS

    layout, kinematics = Layout.default(), PandaKinematics()
    assert "stacked_picks" not in gs.grounding_scene_settings(scenes=2, seed=0, image_size=32)
    assert gs.grounding_scene_settings(scenes=2, seed=0, image_size=32, stacked_picks=0.3)["stacked_picks"] == 0.3
    with pytest.raises(ValueError, match="stacked_picks must be a fraction"):
        gs.grounding_scene_settings(scenes=2, seed=0, image_size=32, stacked_picks=-0.1)
    for index in range(12):  # two scenes of each of the six tasks, at the start and along the approach
        plain = gs.sample_grounding_scene(index, 5, layout, kinematics)
        stacked = gs.sample_grounding_scene(index, 5, layout, kinematics, 0.0, 1.0)
        assert not plain["stacked_pick"]
        if stacked["task"] not in STACKED_PICK_TASKS:  # the other tasks' scenes are drawn as before
            assert not stacked["stacked_pick"] and stacked["instruction"] == plain["instruction"]
            np.testing.assert_array_equal(stacked["state"], plain["state"])
            continue
        scene = scene_from_spec(stacked["spec"], layout)
        label = stacked["subgoal_position"]
        under_label = [c for c in stacked["spec"].blocks if np.linalg.norm(scene.block_position(c)[:2] - label[:2]) < 0.01]
        picked = max(under_label, key=lambda c: scene.block_position(c)[2])  # a stack's blocks share their x-y
        base = scene.base_of(picked)
        assert stacked["stacked_pick"] and base is not None and picked in stacked["instruction"], stacked["instruction"]
        top = scene.block_position(picked)
        assert top[2] > scene.block_position(base)[2] + 0.9 * BLOCK_SIZE
        # The label is the plan's grasp of the top block: at its height, above its centre in x-y.
        assert abs(stacked["subgoal_position"][2] - plain["subgoal_position"][2] - BLOCK_SIZE) < 0.01
        assert np.linalg.norm(stacked["subgoal_position"][:2] - top[:2]) < 0.01


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
            state=state, subgoal_position=(np.array([0.5, 0.0, 0.03]) + 0.05 * rng.normal(size=(n, 3))).astype(np.float32),
            subgoal_yaw=np.zeros((n, 2), dtype=np.float32), stacked_pick=np.zeros(n, dtype=bool))
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


def _stacked_and_plain_samples(model, n: int = 24) -> tuple:
    """Scenes half of which (the first half) pick a stacked block, labelled 9 cm higher, and frames."""
    rng = np.random.default_rng(1)

    def samples(count, words, stacked):
        state = np.zeros((count, 18), dtype=np.float32)
        state[:, :7], state[:, 7:9] = HOME_ARM_Q, gs.FINGER_OPEN
        views = rng.integers(0, 255, size=(2, count, model.image_size, model.image_size, 3), dtype=np.uint8)
        position = np.array([0.5, 0.0, 0.03]) + 0.03 * rng.normal(size=(count, 3)) + 0.09 * stacked[:, None] * [0, 0, 1]
        return refit.scene_samples(model, SimpleNamespace(
            folder="memory", static=views[0], wrist=views[1], instructions=[words] * count, tasks=["lift_block"] * count,
            state=state, subgoal_position=position.astype(np.float32), subgoal_yaw=np.zeros((count, 2), np.float32),
            stacked_pick=stacked), progress=False)

    return (samples(n, "lift the red block", np.arange(n) < n // 2),
            samples(12, "put the blue block in the bowl please", np.zeros(12, dtype=bool)))


def test_stacked_share_draws_that_part_of_the_scenes_from_the_stacked_picks():
    model = _grounded_model()
    scenes, frames = _stacked_and_plain_samples(model)
    assert scenes.stacked.sum() == 12 and frames.stacked_rows().sum() == 0
    rows = refit._scene_rows(scenes, 8, 0.75, torch.Generator().manual_seed(0))
    assert scenes.stacked[rows].tolist() == [True] * 6 + [False] * 2
    for share in (0.0, 1.0):
        with pytest.raises(ValueError, match="stacked_share must be in"):
            refit.refit_readout(model, scenes, frames, steps=1, lr=1e-3, stacked_share=share)
    with pytest.raises(ValueError, match="0 of the 12 scenes do"):
        refit.refit_readout(model, frames, frames, steps=1, lr=1e-3, stacked_share=0.5)
    with pytest.raises(ValueError, match="hold_weight must be >= 0"):
        refit.refit_readout(model, scenes, frames, steps=1, lr=1e-3, hold_weight=-1.0)
    with pytest.raises(ValueError, match="goal_hold_weight must be >= 0"):
        refit.refit_readout(model, scenes, frames, steps=1, lr=1e-3, goal_hold_weight=-1.0)


def test_hold_keeps_the_answers_of_samples_that_pick_no_stacked_block_closer_to_where_they_were():
    moved = {}
    for hold in (0.0, 20.0):
        model = _grounded_model()
        scenes, frames = _stacked_and_plain_samples(model)
        before = refit.raw_subgoals(model, scenes)
        refit.refit_readout(model, scenes, frames, steps=40, lr=3e-3, batch_size=8, stacked_share=0.5,
                            hold_weight=hold, progress=False)
        change = (refit.raw_subgoals(model, scenes) - before).norm(dim=1)
        moved[hold] = (float(change[~scenes.stacked].mean()), float(change[scenes.stacked].mean()))
        assert not any(p.requires_grad for p in model.parameters())
    assert moved[20.0][0] < 0.5 * moved[0.0][0]  # the table scenes stay nearer their old answers...
    assert moved[20.0][1] > moved[20.0][0]  # ...while the stacked picks still move


def test_the_groundings_outputs_are_the_goal_token_the_dit_reads_and_the_subgoal():
    model = _grounded_model()
    scenes, _ = _stacked_and_plain_samples(model, n=6)
    goals, subgoals = refit.grounding_outputs(model, scenes, batch_size=4)
    assert goals.shape == (6, model.config.policy.hidden_size) and subgoals.shape[0] == 6
    torch.testing.assert_close(subgoals, refit.raw_subgoals(model, scenes))
    b = scenes.batch(torch.arange(6), scenes.q_vl.shape[1])
    with torch.no_grad():
        torch.testing.assert_close(subgoals, model.subgoal_of_features(b["q_vl"], b["q_vl_mask"], b["state"]).float())
    moved = refit.goal_drift(goals, 1.5 * goals)
    torch.testing.assert_close(moved, torch.full((6,), 0.5))
    assert refit.goal_drift(goals, goals).abs().max() == 0


def test_goal_hold_keeps_the_goal_token_of_samples_that_pick_no_stacked_block_nearer_where_it_was():
    drift = {}
    for goal_hold in (0.0, 50.0):
        model = _grounded_model()
        scenes, frames = _stacked_and_plain_samples(model)
        before = refit.grounding_outputs(model, scenes)[0]
        refit.refit_readout(model, scenes, frames, steps=40, lr=3e-3, batch_size=8, stacked_share=0.5,
                            goal_hold_weight=goal_hold, progress=False)
        moved = refit.goal_drift(before, refit.grounding_outputs(model, scenes)[0])
        drift[goal_hold] = (float(moved[~scenes.stacked].mean()), float(moved[scenes.stacked].mean()))
    assert drift[0.0][0] > 0  # unheld, the re-fit moves what System 1 reads...
    assert drift[50.0][0] < 0.5 * drift[0.0][0]  # ...held, the table scenes' goal tokens stay nearer
    model = _grounded_model()
    torch.nn.init.zeros_(model.policy.grounding.goal[2].weight)  # a goal projection at its zero start: nothing to hold
    curve = refit.refit_readout(model, scenes, frames, steps=4, lr=1e-3, batch_size=8, log_every=2, stacked_share=0.5,
                                hold_weight=1.0, goal_hold_weight=1.0, progress=False)
    assert all(np.isfinite(loss) for _, loss in curve)


def test_saved_samples_load_back_and_a_broken_file_is_named(tmp_path):
    model = _grounded_model()
    scenes, _ = _stacked_and_plain_samples(model, n=4)
    refit.save_samples(scenes, tmp_path / "q" / "scenes.pt")
    assert [p.name for p in (tmp_path / "q").iterdir()] == ["scenes.pt"]  # no partial file left
    loaded = refit.load_samples(tmp_path / "q" / "scenes.pt")
    for name in ("q_vl", "q_vl_mask", "state", "subgoal_position", "subgoal_yaw", "stacked"):
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
    from trivla_drake.data.lerobot import LeRobotReader
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


def test_the_refit_script_saves_a_model_whose_grounding_alone_changed_and_reports_its_errors(
        tmp_path, monkeypatch, results_script, capsys):
    from trivla_drake.nn import load_checkpoint
    from trivla_drake.nn.checkpoint import save_checkpoint
    from trivla_drake.nn.normalization import NormalizationStats
    from trivla_drake.train.synthetic import write_synthetic_dataset

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the rendered scenes go there
    model = _grounded_model()
    rng = np.random.default_rng(0)
    model.set_normalization(NormalizationStats.from_data(rng.normal(size=(50, 18)), rng.uniform(-0.05, 0.05, (50, 10, 7))))
    save_checkpoint(model, str(tmp_path / "in"))
    data = write_synthetic_dataset(tmp_path / "d", episodes=2, length=10, image_size=16, tcp_pose=True)
    script = results_script("grounding_scenes/refit_grounding.py")
    monkeypatch.setattr("sys.argv", ["refit_grounding.py", str(tmp_path / "in"), data, str(tmp_path / "out"),
                                     "--scenes", "4", "--test-scenes", "2", "--chain-starts", "0.5", "--stacked-picks", "0.5",
                                     "--steps", "3", "--lr", "0.01", "--threads", "1", "--hold", "0.5",
                                     "--goal-hold", "0.5", "--report", str(tmp_path / "report")])
    script.main()
    assert "Q_vl of" not in capsys.readouterr().out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["samples"] == {"scenes": 4, "test_scenes": 2, "test_chain_starts": 2, "test_stacked_picks": 2,
                                 "data_frames": 4}
    for test in ("test_scenes", "test_chain_starts", "test_stacked_picks"):
        assert set(report["median_and_p90_xy_error_cm"]["after"][test]) == {"all", "lift_block"}
        assert set(report["median_z_error_cm"]["after"][test]) == {"all", "lift_block"}
        assert set(report["median_goal_drift"][test]) == {"all", "lift_block"}
    assert report["settings"]["goal_hold"] == 0.5 and report["median_goal_drift"]["data_frames"]["all"] >= 0
    assert (tmp_path / "report.loss.png").stat().st_size > 0
    sets = list((tmp_path / "cache" / "trivla_drake" / "train" / "grounding_scenes").iterdir())
    assert len(sets) == 4  # training (half chain starts, half stacked picks), plain, chain-start and stacked tests
    metas = [json.loads((f / "meta.json").read_text()) for f in sets]
    assert sorted((m.get("chain_starts", 0.0), m.get("stacked_picks", 0.0)) for m in metas) == [
        (0.0, 0.0), (0.0, 1.0), (0.5, 0.5), (1.0, 0.0)]
    stacked_test = next(f for f, m in zip(sets, metas) if m.get("stacked_picks") == 1.0)
    assert gs.GroundingScenes(stacked_test).stacked_pick.all()  # both test scenes are lifts off a stack
    before, after = load_checkpoint(str(tmp_path / "in")).state_dict(), load_checkpoint(str(tmp_path / "out")).state_dict()
    readout = {f"policy.{name}" for name in refit.readout_parameters(model)}
    changed = {k for k in before if not torch.allclose(before[k].float(), after[k].float(), atol=1e-3)}
    assert changed and changed <= readout
    # Q_vl of the five sets (training, three tests, the data's frames) was kept; a second run reads it back.
    assert len(list((tmp_path / "cache" / "trivla_drake" / "train" / "grounding_q_vl").glob("*.pt"))) == 5
    script.main()
    assert capsys.readouterr().out.count("Q_vl of") == 5
    again = json.loads((tmp_path / "report.json").read_text())
    assert again["median_and_p90_xy_error_cm"]["before"] == report["median_and_p90_xy_error_cm"]["before"]


def test_the_occlusion_script_bins_each_models_errors_by_how_much_of_the_block_the_static_camera_sees(
        tmp_path, monkeypatch, results_script, capsys):
    from trivla_drake.nn.checkpoint import save_checkpoint

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    save_checkpoint(_grounded_model(), str(tmp_path / "model"))
    script = results_script("grounding_scenes/chain_starts/occlusion.py")
    assert script.first_color("place the blue block onto the red block") == "blue"
    monkeypatch.setattr("sys.argv", ["occlusion.py", str(tmp_path / "out.json"), f"tiny={tmp_path / 'model'}",
                                     "--scenes", "3", "--threads", "1"])
    script.main()
    report = json.loads((tmp_path / "out.json").read_text())
    assert len(report["static_pixels"]) == len(report["error_cm"]["tiny"]) == 3
    assert sum(report["static_pixels"]) + sum(report["wrist_pixels"]) > 0  # the blocks are seen somewhere
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith("| static-view pixels") and len(table) == 2 + len(script.BINS)
    assert sum(int(row.split("|")[2]) for row in table[2:]) == 3


def test_the_true_subgoal_after_a_prelude_diagnostic_runs_the_grasp_tasks_after_one_prelude_task(
        tmp_path, monkeypatch, results_script, capsys):
    from trivla_drake.eval import evaluate as ev
    from trivla_drake.nn.checkpoint import save_checkpoint

    save_checkpoint(_grounded_model(), str(tmp_path / "model"))
    script = results_script("grounding_scenes/chain_starts/true_subgoal_prelude.py")
    configs = []

    def fake_evaluate(config, progress=True):  # the episodes themselves are the evaluation's (tests/test_evaluate*)
        configs.append(config)
        assert ev._policy(*config.policy_key()).privileged  # the oracle's grasp position needs the scene
        return {"tasks": {t: {"successes": 1} for t in config.tasks}}

    monkeypatch.setattr(ev, "evaluate", fake_evaluate)
    monkeypatch.setattr("sys.argv", ["true_subgoal_prelude.py", "1000,1002", str(tmp_path / "true"), str(tmp_path / "model")])
    try:
        script.main()
    finally:
        ev._POLICY_CACHE.pop(ev.EvalConfig(policy="trivla").policy_key(), None)
    assert [(c.seed, c.prelude, c.episodes, c.workers) for c in configs] == [(1000, 1, 2, 1), (1002, 1, 2, 1)]
    assert configs[0].tasks == script.TASKS
    assert json.loads((tmp_path / "true_seed1002.json").read_text())["tasks"]["lift_block"]["successes"] == 1
    assert "1002" in capsys.readouterr().out


def test_the_stacked_subgoal_diagnostic_replaces_only_its_axes_and_records_the_groundings_own_subgoal(
        tmp_path, monkeypatch, results_script):
    from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy
    from trivla_drake.nn.checkpoint import save_checkpoint
    from trivla_drake.nn.panda_tcp import denormalize_position

    model = _grounded_model()
    model = TriVLA(dataclasses.replace(model.config, policy=dataclasses.replace(
        model.config.policy, subgoal_offset=True))).eval()
    save_checkpoint(model, str(tmp_path / "model"))
    script = results_script("stacked_subgoal/stacked_subgoal.py")
    size = model.image_size
    rng = np.random.default_rng(0)
    observation = {"static_rgb": rng.integers(0, 255, (size, size, 3), dtype=np.uint8),
                   "wrist_rgb": rng.integers(0, 255, (size, size, 3), dtype=np.uint8),
                   "state": np.concatenate([HOME_ARM_Q, [0.04, 0.04], np.zeros(9)]).astype(np.float32)}
    true = np.array([0.55, 0.12, 0.0725])

    def chunk(axes):
        """The chunk, the policy, and the sub-goal [m] System 1's offset path read."""
        policy = script.StackedSubgoal.from_checkpoint(str(tmp_path / "model"))
        policy.axes = axes
        policy.reset("lift the red block", 3)
        policy.true = true
        read = []
        policy.model.policy.subgoal_offset.register_forward_pre_hook(
            lambda module, args: read.append(denormalize_position(args[0][0, :3].detach().float()).numpy()))
        return TriVLAHarnessPolicy.act(policy, observation), policy, read[0]  # TrueSubgoal.act would read the scene

    plain = TriVLAHarnessPolicy.from_checkpoint(str(tmp_path / "model"))
    plain.reset("lift the red block", 3)
    own, recorded, read = chunk(())
    np.testing.assert_allclose(own, plain.act(observation), atol=1e-6)  # nothing replaced: the model's own
    assert [r["episode"] for r in recorded.records] == [0] and recorded.records[0]["true"] == true.tolist()
    predicted = np.array(recorded.records[0]["predicted"])
    np.testing.assert_allclose(read, predicted, atol=1e-5)
    np.testing.assert_allclose(chunk((0, 1, 2))[2], true, atol=1e-5)
    _, height_only, read = chunk((2,))
    np.testing.assert_allclose(read, [predicted[0], predicted[1], true[2]], atol=1e-5)
    # Every mode records the grounding's own sub-goal, whatever System 1 is given.
    np.testing.assert_allclose(height_only.records[0]["predicted"], predicted, atol=1e-6)
    rows = [{"episode": 0, "predicted": [0.0, 0.0, 0.0], "true": [0.03, 0.04, 0.04]},
            {"episode": 0, "predicted": [0.0, 0.0, 0.1], "true": [0.0, 0.0, 0.0]},
            {"episode": 1, "predicted": [0.0, 0.0, 0.0], "true": [0.0, 0.0, 0.02]}]
    summary = script.summarise(rows)
    assert summary["first_chunk"]["chunks"] == 2 and summary["every_chunk"]["chunks"] == 3
    assert summary["first_chunk"]["dz_median_cm"] == pytest.approx(-3.0)
    assert summary["first_chunk"]["xy_median_cm"] == pytest.approx(2.5)
    monkeypatch.setattr("sys.argv", ["stacked_subgoal.py", "x", "1000", str(tmp_path)])
    with pytest.raises(SystemExit, match="MODE must be one of"):
        script.main()


def test_the_stack_probe_fits_a_logistic_regression_per_view_and_scores_it_on_unseen_scenes(
        tmp_path, monkeypatch, results_script):
    from trivla_drake.nn.checkpoint import save_checkpoint

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    save_checkpoint(_grounded_model(), str(tmp_path / "model"))
    script = results_script("stacked_hold/stack_probe.py")
    argv = ["stack_probe.py", str(tmp_path / "model"), str(tmp_path / "probe.json"), "--scenes", "12",
            "--test-scenes", "6", "--stacked-picks", "0.5", "--steps", "20"]
    monkeypatch.setattr("sys.argv", argv)
    script.main()
    report = json.loads((tmp_path / "probe.json").read_text())
    assert set(report["probes"]) == {"static", "wrist", "both"}
    assert report["train"]["stacked"] > 0 and report["train"]["plain"] > 0
    assert report["test"]["stacked"] > 0 and report["test"]["plain"] > 0
    for probe in report["probes"].values():
        for scored in probe.values():
            assert 0.0 <= scored["accuracy"] <= 1.0
            assert abs(scored["balanced_accuracy"] - (scored["stacked_recall"] + scored["plain_recall"]) / 2) < 2e-3
    assert report["probes"]["both"]["training"]["accuracy"] > 0.5  # 20 steps fit a few training scenes
    monkeypatch.setattr("sys.argv", argv[:4] + ["1", "--test-scenes", "6", "--stacked-picks", "0.5", "--steps", "1"])
    with pytest.raises(SystemExit, match="all of one kind"):  # one training scene: a single class
        script.main()
