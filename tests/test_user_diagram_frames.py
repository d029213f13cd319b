"""A user's own diagram with the Panda's base moved and turned: `ee_target` is in the world, the diff-IK maps it
back, and the same actions move the hand the same way relative to its base as at the origin; the diff-IK reports
a hand that does not follow its target."""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem

from trivla_drake import DifferentialIKSystem
from trivla_drake.robot.panda_kinematics import PandaKinematics
from trivla_drake.systems.action_chunk_executor import ActionChunkExecutor

DT = 1.0 / 36.0
# 10 cm up, moved in x and y, turned 90 degrees about the vertical.
MOVED = RigidTransform(RollPitchYaw(0.0, 0.0, np.pi / 2), [0.3, -0.2, 0.1])
HOME_Q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785])


def load_example():
    """examples/user_diagram.py as a module (its `add_user_world` builds the user's plant)."""
    path = Path(__file__).resolve().parents[1] / "examples" / "user_diagram.py"
    spec = importlib.util.spec_from_file_location("user_diagram", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class ChunkStream(LeafSystem):
    """A stand-in for System 1: at every control tick, a chunk of one repeated action observed at that tick."""

    def __init__(self, action):
        super().__init__()
        chunk = np.tile(np.asarray(action, dtype=float), (10, 1))
        self.DeclareAbstractOutputPort("action_chunk", lambda: AbstractValue.Make(chunk),
                                       lambda context, output: output.set_value(chunk))
        self.DeclareVectorOutputPort("action_chunk_stamp", 1, self._stamp)

    def _stamp(self, context, output: BasicVector):
        output.SetAtIndex(0, np.floor(context.get_time() / DT + 1e-6) * DT)


def _scripted_run(X_WB, action, seconds=1.0):
    """The user's world (examples/user_diagram.py, no cameras) driven by the chunk executor and diff-IK given
    X_WB; returns the hand's pose in the base frame and in the world and the diff-IK's tracking error at each
    0.1 s, ee_target at initialisation and the hand's pose in the world at the start."""
    builder = DiagramBuilder()
    world = load_example().add_user_world(builder, X_WB, image_size=None)
    stream = builder.AddSystem(ChunkStream(action))
    executor = builder.AddSystem(ActionChunkExecutor(X_WB=X_WB))
    diffik = builder.AddSystem(DifferentialIKSystem(X_WB=X_WB))
    builder.Connect(stream.GetOutputPort("action_chunk"), executor.GetInputPort("action_chunk"))
    builder.Connect(stream.GetOutputPort("action_chunk_stamp"), executor.GetInputPort("action_chunk_stamp"))
    builder.Connect(world.robot_state, executor.GetInputPort("robot_state"))
    builder.Connect(world.robot_state, diffik.GetInputPort("robot_state"))
    builder.Connect(executor.GetOutputPort("ee_target"), diffik.GetInputPort("ee_target"))
    builder.Connect(diffik.GetOutputPort("position_setpoint"), world.arm_position)
    builder.Connect(executor.GetOutputPort("gripper_target"), world.gripper_width)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.Initialize()
    context = simulator.get_mutable_context()
    plant, plant_context = world.plant, world.plant.GetMyContextFromRoot(context)
    base = plant.GetFrameByName("panda_link0", world.panda)
    hand = plant.GetFrameByName("panda_hand_tcp", world.panda)
    first_target = executor.GetOutputPort("ee_target").Eval(executor.GetMyContextFromRoot(context)).GetAsMatrix4()
    in_base, in_world, tracking = [], [], []
    for t in np.arange(0.0, seconds + 1e-9, 0.1):
        simulator.AdvanceTo(t)
        in_base.append(plant.CalcRelativeTransform(plant_context, base, hand).GetAsMatrix4())
        in_world.append(hand.CalcPoseInWorld(plant_context).GetAsMatrix4())
        tracking.append(diffik.GetOutputPort("tracking_error").Eval(diffik.GetMyContextFromRoot(context)).copy())
    hand_at_start = hand.CalcPoseInWorld(plant.CreateDefaultContext())
    return np.array(in_base), np.array(in_world), np.array(tracking), first_target, hand_at_start


# Forward 4 mm, left 2 mm, up 3 mm and 0.02 rad about the base's z a step; the gripper open.
ACTION = [0.004, 0.002, 0.003, 0.0, 0.0, 0.02, 1.0]


@pytest.fixture(scope="module")
def at_origin():
    return _scripted_run(RigidTransform(), ACTION)


def test_ee_target_starts_at_the_measured_hand_in_the_world():
    *_, first_target, hand_at_start = _scripted_run(MOVED, ACTION, seconds=0.0)
    np.testing.assert_allclose(first_target, hand_at_start.GetAsMatrix4(), atol=1e-6)


def test_a_moved_and_turned_base_moves_the_hand_as_at_the_origin(at_origin):
    """The same actions give the same hand trajectory relative to the base; in the world it is that trajectory
    carried by X_WB (it rises as the actions say: no dive)."""
    in_base_origin = at_origin[0]
    in_base, in_world, tracking, _, _ = _scripted_run(MOVED, ACTION)
    assert in_base_origin[-1][2, 3] - in_base_origin[0][2, 3] > 0.05  # the actions did lift the hand
    np.testing.assert_allclose(in_base[:, :3, 3], in_base_origin[:, :3, 3], atol=3e-3)
    np.testing.assert_allclose(in_base[:, :3, :3], in_base_origin[:, :3, :3], atol=1e-2)
    np.testing.assert_allclose(in_world, MOVED.GetAsMatrix4() @ in_base_origin, atol=3e-3)
    assert np.all(tracking[1:, 0] < 0.05)  # the hand follows its world-frame target closely


def _fixed_diffik(**kwargs):
    """A DifferentialIKSystem whose robot state never changes (a driver that never moves the arm)."""
    diffik = DifferentialIKSystem(**kwargs)
    context = diffik.CreateDefaultContext()
    diffik.GetInputPort("robot_state").FixValue(context, np.concatenate([HOME_Q, [0.04, 0.04], np.zeros(9)]))
    simulator = Simulator(diffik, context)
    return diffik, context, simulator


def _hand_in_world(X_WB=RigidTransform()):
    return X_WB @ RigidTransform(PandaKinematics().ee_pose(HOME_Q))


def test_a_hand_that_does_not_follow_is_reported_once_then_again_after_recovering(caplog):
    diffik, context, simulator = _fixed_diffik(X_WB=MOVED)
    hand = _hand_in_world(MOVED)
    far = RigidTransform(hand.rotation(), hand.translation() + [0.0, 0.0, 0.1])
    diffik.GetInputPort("ee_target").FixValue(context, far)
    with caplog.at_level(logging.WARNING, logger="trivla_drake.systems.diffik_system"):
        simulator.AdvanceTo(0.9)
        assert not caplog.records  # far, but not for a second yet
        simulator.AdvanceTo(2.5)
        distance, angle = diffik.GetOutputPort("tracking_error").Eval(context)
        assert distance == pytest.approx(0.1, abs=1e-9) and angle == pytest.approx(0.0, abs=1e-9)
        assert diffik.GetOutputPort("status").Eval(context)[0] == 0.0  # the QP itself keeps solving
        assert len(caplog.records) == 1 and "tracking_error" in caplog.records[0].getMessage()
        # Back on target (in the world, the base moved: the error is computed in one frame) ...
        diffik.GetInputPort("ee_target").FixValue(context, hand)
        simulator.AdvanceTo(2.7)
        np.testing.assert_allclose(diffik.GetOutputPort("tracking_error").Eval(context), [0.0, 0.0], atol=1e-9)
        # ... and far again: a new warning after another second.
        diffik.GetInputPort("ee_target").FixValue(context, far)
        simulator.AdvanceTo(3.6)
        assert len(caplog.records) == 1
        simulator.AdvanceTo(3.8)
        assert len(caplog.records) == 2


def test_the_tracking_warning_thresholds_are_settings(caplog):
    diffik, context, simulator = _fixed_diffik(tracking_warning_distance_m=0.2, tracking_warning_after_s=0.1)
    hand = _hand_in_world()
    diffik.GetInputPort("ee_target").FixValue(context, RigidTransform(hand.rotation(), hand.translation() + 0.1))
    with caplog.at_level(logging.WARNING, logger="trivla_drake.systems.diffik_system"):
        simulator.AdvanceTo(0.5)
        distance, _ = diffik.GetOutputPort("tracking_error").Eval(context)
        assert distance == pytest.approx(0.1 * np.sqrt(3), abs=1e-9)  # below 0.2 m: no warning state
        assert np.isnan(context.get_discrete_state(1).value()[2])
        assert not caplog.records
        # Farther than 0.2 m: warned once the hand has stayed far for 0.1 s, long before the default 1 s.
        diffik.GetInputPort("ee_target").FixValue(context, RigidTransform(hand.rotation(), hand.translation() + 0.2))
        simulator.AdvanceTo(0.55)
        assert not caplog.records
        simulator.AdvanceTo(0.65)
        assert len(caplog.records) == 1 and "tracking_error" in caplog.records[0].getMessage()


def test_the_tracking_check_can_be_turned_off(caplog):
    diffik, context, simulator = _fixed_diffik(warn_tracking=False, tracking_warning_after_s=0.1)
    hand = _hand_in_world()
    diffik.GetInputPort("ee_target").FixValue(context, RigidTransform(hand.rotation(), hand.translation() + 0.3))
    with caplog.at_level(logging.DEBUG, logger="trivla_drake.systems.diffik_system"):
        simulator.AdvanceTo(2.0)
    assert not caplog.records
    assert np.isnan(diffik.GetOutputPort("tracking_error").Eval(context)).all()  # documented: NaN when off
    assert diffik.GetOutputPort("status").Eval(context)[0] == 0.0


def test_the_pose_only_forward_kinematics_is_ee_pose():
    kinematics = PandaKinematics()
    rng = np.random.default_rng(0)
    for q in [HOME_Q, *rng.uniform(kinematics.q_lower, kinematics.q_upper, size=(20, 7))]:
        np.testing.assert_allclose(kinematics.pose(q), kinematics.ee_pose(q), rtol=0, atol=1e-12)


@pytest.mark.parametrize("kwargs, match", [
    (dict(tracking_warning_distance_m=0.0), "tracking_warning_distance_m"),
    (dict(tracking_warning_after_s=float("nan")), "tracking_warning_after_s"),
    (dict(X_WB=np.eye(4)), "X_WB must be a pydrake.math.RigidTransform"),
    (dict(warn_tracking=1), "warn_tracking"),
])
def test_bad_diffik_settings_name_the_argument(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        DifferentialIKSystem(**kwargs)


def test_the_diffik_maps_a_world_target_into_the_moved_base():
    diffik, context, simulator = _fixed_diffik(X_WB=MOVED)
    diffik.GetInputPort("ee_target").FixValue(context, _hand_in_world(MOVED))
    simulator.AdvanceTo(0.05)
    np.testing.assert_allclose(diffik.GetOutputPort("tracking_error").Eval(context), [0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(diffik.GetOutputPort("position_setpoint").Eval(context), HOME_Q, atol=1e-6)
