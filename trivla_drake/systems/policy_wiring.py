"""`add_trivla_policy`: put a TriVLAPolicy and its diff-IK on any station-like diagram, or on the ports of a
flat diagram of one's own, in one call."""

from __future__ import annotations

from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder, InputPort, OutputPort, System

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.robot.osqp_diffik import DiffIKParams
from trivla_drake.systems.diffik_system import DifferentialIKSystem
from trivla_drake.systems.trivla_policy import PolicyRates, TriVLAPolicy


def add_trivla_policy(
    builder: DiagramBuilder,
    station: System | None,
    model: TriVLA,
    *,
    rates: PolicyRates | None = None,
    seed: int = 0,
    static_camera: str | OutputPort = "static_camera.rgb_image_now",
    wrist_camera: str | OutputPort = "wrist_camera.rgb_image_now",
    robot_state: str | OutputPort = "panda.state",
    arm_position: str | InputPort = "panda.position",
    gripper_width: str | InputPort = "panda.gripper_width",
    X_WB: RigidTransform | None = None,
    diffik_params: DiffIKParams | None = None,
    name: str = "trivla_policy",
    warn_tracking: bool = True,
) -> TriVLAPolicy:
    """Add the policy and a DifferentialIKSystem (named `{name}_diffik`) to `builder` and wire them.

    Each of the five connections is a port name on `station` (make_station's by default) or the port
    itself, an OutputPort (`static_camera`, `wrist_camera`: ImageRgba8U of the model's size; `robot_state`:
    the Panda's 18-vector state) or InputPort (`arm_position`: 7 arm joint setpoints [rad]; `gripper_width`:
    finger distance [m]) of any system in `builder`; with all five given as ports, `station` may be None.
    `X_WB` is the robot base's (`panda_link0`'s) pose in the world, identity by default; read it from your
    plant with `robot_base_pose(plant, panda_instance)`. The cameras default to the `.rgb_image_now`
    ports, rendered when Systems 2 and 3 read them at their ticks, so the images show the same instant as
    the robot state, as in the demonstrations; a held `.rgb_image` port would hand the policy a frame up to
    1/fps old. The policy's `instruction` input is left for the caller to connect (a ConstantValueSource
    of a str, or a task's instruction source). `warn_tracking=False` turns off the diff-IK's "hand far from
    its target" check (for harnesses whose hand is pressed on a block on purpose).
    """
    ports = {}
    for argument, value, kind in (("static_camera", static_camera, OutputPort),
                                  ("wrist_camera", wrist_camera, OutputPort),
                                  ("robot_state", robot_state, OutputPort),
                                  ("arm_position", arm_position, InputPort),
                                  ("gripper_width", gripper_width, InputPort)):
        ports[argument] = _port(station, argument, value, kind)
    policy = builder.AddNamedSystem(name, TriVLAPolicy(model, rates, seed=seed, X_WB=X_WB))
    diffik = builder.AddNamedSystem(f"{name}_diffik", DifferentialIKSystem(diffik_params, X_WB=X_WB,
                                                                                  warn_tracking=warn_tracking))
    builder.Connect(ports["static_camera"], policy.GetInputPort("static_rgb"))
    builder.Connect(ports["wrist_camera"], policy.GetInputPort("wrist_rgb"))
    builder.Connect(ports["robot_state"], policy.GetInputPort("robot_state"))
    builder.Connect(ports["robot_state"], diffik.GetInputPort("robot_state"))
    builder.Connect(policy.GetOutputPort("ee_target"), diffik.GetInputPort("ee_target"))
    builder.Connect(diffik.GetOutputPort("position_setpoint"), ports["arm_position"])
    builder.Connect(policy.GetOutputPort("gripper_target"), ports["gripper_width"])
    return policy


def _port(station: System | None, argument: str, value, kind):
    """`value` itself when it is a port of the right direction, else the port of that name on `station`."""
    if isinstance(value, kind):
        return value
    direction = "output" if kind is OutputPort else "input"
    if not isinstance(value, str):
        raise TypeError(f"add_trivla_policy {argument} must be a port name (str) or an {kind.__name__}, got "
                        f"{type(value).__name__}")
    if station is None:
        raise ValueError(f"add_trivla_policy {argument}={value!r} names a port but station is None: pass the "
                         f"{kind.__name__} itself, or the station that has it")
    has = station.HasOutputPort if kind is OutputPort else station.HasInputPort
    if not has(value):
        count = station.num_output_ports() if kind is OutputPort else station.num_input_ports()
        get = station.get_output_port if kind is OutputPort else station.get_input_port
        names = [get(i).get_name() for i in range(count)]
        raise ValueError(f"add_trivla_policy {argument}: '{station.get_name()}' has no {direction} port {value!r}; "
                         f"its {direction} ports are {names}")
    return station.GetOutputPort(value) if kind is OutputPort else station.GetInputPort(value)
