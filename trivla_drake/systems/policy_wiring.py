"""`add_trivla_policy`: put a TriVLAPolicy and its diff-IK on any station-like diagram in one call."""

from __future__ import annotations

from pydrake.systems.framework import DiagramBuilder, System

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.robot.osqp_diffik import DiffIKParams
from trivla_drake.systems.diffik_system import DifferentialIKSystem
from trivla_drake.systems.trivla_policy import PolicyRates, TriVLAPolicy


def add_trivla_policy(
    builder: DiagramBuilder,
    station: System,
    model: TriVLA,
    *,
    rates: PolicyRates | None = None,
    seed: int = 0,
    static_camera: str = "static_camera.rgb_image_now",
    wrist_camera: str = "wrist_camera.rgb_image_now",
    robot_state: str = "panda.state",
    arm_position: str = "panda.position",
    gripper_width: str = "panda.gripper_width",
    diffik_params: DiffIKParams | None = None,
    name: str = "trivla_policy",
) -> TriVLAPolicy:
    """Add the policy and a DifferentialIKSystem to `builder` and wire them to `station`'s ports.

    The port names default to make_station's; pass others for a different station or robot. The
    cameras default to the `.rgb_image_now` ports, rendered when Systems 2 and 3 read them at their
    ticks, so the images show the same instant as the robot state, as in the demonstrations; a held
    `.rgb_image` port would hand the policy a frame up to 1/fps old.
    The policy's `instruction` input is left for the caller to connect (a ConstantValueSource of a
    str, or a task's instruction source).
    """
    policy = builder.AddNamedSystem(name, TriVLAPolicy(model, rates, seed=seed))
    diffik = builder.AddNamedSystem(f"{name}_diffik", DifferentialIKSystem(diffik_params))
    builder.Connect(station.GetOutputPort(static_camera), policy.GetInputPort("static_rgb"))
    builder.Connect(station.GetOutputPort(wrist_camera), policy.GetInputPort("wrist_rgb"))
    builder.Connect(station.GetOutputPort(robot_state), policy.GetInputPort("robot_state"))
    builder.Connect(station.GetOutputPort(robot_state), diffik.GetInputPort("robot_state"))
    builder.Connect(policy.GetOutputPort("ee_target"), diffik.GetInputPort("ee_target"))
    builder.Connect(diffik.GetOutputPort("position_setpoint"), station.GetInputPort(arm_position))
    builder.Connect(policy.GetOutputPort("gripper_target"), station.GetInputPort(gripper_width))
    return policy
