"""Add TriVLA to a Drake diagram of one's own, without make_station: a MultibodyPlant with the project's Panda
on a 10 cm pedestal, moved and turned 90 degrees, a table and a block placed in front of it, two cameras of
one's own, the instruction from a ConstantValueSource, and Drake's plain Simulator.

    python examples/user_diagram.py --seconds 3
"""

import argparse
from dataclasses import dataclass

import numpy as np
from pydrake.common.schema import Transform
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, InputPort, OutputPort
from pydrake.systems.primitives import ConstantValueSource
from pydrake.systems.sensors import CameraConfig

from trivla_drake import (
    PandaDriverConfig,
    add_panda_driver,
    add_rgb_camera,
    add_trivla_policy,
    drake_panda_urdf,
    load_model,
    make_panda_only_plant,
    make_parser,
    robot_base_pose,
)

# Where the robot's base (panda_link0) stands in the world: 10 cm up, moved, turned 90 degrees about z.
X_WB = RigidTransform(RollPitchYaw(0.0, 0.0, np.pi / 2), [0.3, -0.2, 0.1])
# The arm's start: q (7 arm joints [rad], 2 fingers [m]), the project's home.
HOME = [0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785, 0.04, 0.04]


@dataclass
class UserWorld:
    """What the user's world gives the policy."""

    plant: MultibodyPlant
    panda: object  # the Panda's ModelInstanceIndex
    robot_state: OutputPort  # 18-vector, q then v
    arm_position: InputPort  # 7 arm joint setpoints [rad]
    gripper_width: InputPort  # finger distance [m]
    static_camera: OutputPort | None  # ImageRgba8U, rendered when read
    wrist_camera: OutputPort | None


def look_at(eye, target) -> RigidTransform:
    """A camera pose (Drake's camera frame: +z forward, +y down) at `eye` looking at `target` [m]."""
    z = np.subtract(target, eye) / np.linalg.norm(np.subtract(target, eye))
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return RigidTransform(RotationMatrix(np.column_stack([x, np.cross(z, x), z])), eye)


def add_user_world(builder: DiagramBuilder, X_WB: RigidTransform, *, image_size: int | None = 224) -> UserWorld:
    """The plant (Panda at X_WB, a table and a block in front of it), the Panda's driver and, unless image_size
    is None, a static camera and a wrist camera of that size."""
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=0.004)
    parser = make_parser(plant)  # knows the packages `trivla_panda` and `trivla_drake_models`
    (panda,) = parser.AddModels(str(drake_panda_urdf()))
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("panda_link0", panda), X_WB)
    (table,) = parser.AddModels(url="package://trivla_drake_models/table.sdf")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("table_top", table),
                     X_WB @ RigidTransform([0.35, 0.0, -0.025]))
    (block,) = parser.AddModels(url="package://trivla_drake_models/block_red.sdf")
    plant.SetDefaultFloatingBaseBodyPose(plant.GetBodyByName("block", block),
                                         X_WB @ RigidTransform([0.45, 0.05, 0.0225]))
    plant.Finalize()
    plant.SetDefaultPositions(panda, HOME)

    # The driver's gravity compensation uses a Panda-only plant welded like the simulated one.
    controller_plant = make_panda_only_plant(str(drake_panda_urdf()), parser, X_WB=X_WB)
    arm_position, gripper_width = add_panda_driver(builder, plant, panda, controller_plant, PandaDriverConfig())

    static_camera = wrist_camera = None
    if image_size is not None:
        static = CameraConfig(name="static", width=image_size, height=image_size, focal=CameraConfig.FovDegrees(y=55))
        # Behind the robot's right shoulder, looking at the table in front of it.
        static.X_PB = Transform(look_at(X_WB @ np.array([-0.2, -0.6, 0.7]), X_WB @ np.array([0.45, 0.0, 0.0])))
        wrist = CameraConfig(name="wrist", width=image_size, height=image_size, focal=CameraConfig.FovDegrees(y=75))
        wrist.X_PB = Transform(RigidTransform(RollPitchYaw(np.radians([0.0, -15.0, -90.0])), [0.07, 0.0, 0.02]))
        wrist.X_PB.base_frame = "panda::panda_hand"
        # Each returns (the image held at the camera's fps, the image rendered when read): the policy reads the latter.
        static_camera = add_rgb_camera(builder, plant, scene_graph, "static", static)[1]
        wrist_camera = add_rgb_camera(builder, plant, scene_graph, "wrist", wrist)[1]
    return UserWorld(plant, panda, plant.get_state_output_port(panda), arm_position, gripper_width,
                     static_camera, wrist_camera)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint")
    parser.add_argument("--preset", default=None,
                        help="use an UNTRAINED model of this preset (tiny, cpu) instead of the shipped checkpoint")
    parser.add_argument("--seconds", type=float, default=3.0)
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    model = load_model(args.checkpoint, preset=args.preset)

    builder = DiagramBuilder()
    world = add_user_world(builder, X_WB, image_size=model.image_size)
    policy = add_trivla_policy(
        builder, None, model,
        static_camera=world.static_camera, wrist_camera=world.wrist_camera, robot_state=world.robot_state,
        arm_position=world.arm_position, gripper_width=world.gripper_width,
        X_WB=robot_base_pose(world.plant, world.panda),  # read from the weld: the same as X_WB above
    )
    instruction = builder.AddNamedSystem("instruction", ConstantValueSource(AbstractValue.Make("lift the red block")))
    builder.Connect(instruction.get_output_port(), policy.GetInputPort("instruction"))
    diagram = builder.Build()

    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant_context = world.plant.GetMyContextFromRoot(context)
    hand = world.plant.GetFrameByName("panda_hand_tcp", world.panda)
    start = hand.CalcPoseInWorld(plant_context).translation().copy()
    simulator.AdvanceTo(args.seconds)
    end = hand.CalcPoseInWorld(plant_context).translation()
    target = policy.GetOutputPort("ee_target").Eval(policy.GetMyContextFromRoot(context)).translation()
    diffik = diagram.GetSubsystemByName("trivla_policy_diffik")
    distance, angle = diffik.GetOutputPort("tracking_error").Eval(diffik.GetMyContextFromRoot(context))
    print(f"hand (world) {np.round(start, 3)} -> {np.round(end, 3)} m; ee_target (world) {np.round(target, 3)} m; "
          f"tracking error {distance:.3f} m, {angle:.3f} rad")


if __name__ == "__main__":
    main()
