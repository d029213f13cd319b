"""Compose TriVLA into a larger diagram than the project's station: an extra object, a moved static
camera, a third camera for the user, and a system of the user's own watching the scene.

    python examples/compose_larger_diagram.py --seconds 3
"""

import argparse

import numpy as np
import torch
from pydrake.common.schema import Transform
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.parsing import AddModel, ModelDirective
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantValueSource
from pydrake.systems.sensors import CameraConfig

from trivla_drake import add_trivla_policy, load_model, load_scenario, make_simulator, make_station


class HandToBlockDistance(LeafSystem):
    """The user's own system: distance [m] from the hand target to the extra block, at 10 Hz."""

    def __init__(self, plant, block_body):
        super().__init__()
        self._plant, self._block = plant, block_body
        self._poses = self.DeclareAbstractInputPort("body_poses", AbstractValue.Make([RigidTransform()]))
        self._target = self.DeclareAbstractInputPort("ee_target", AbstractValue.Make(RigidTransform()))
        index = self.DeclareDiscreteState(1)
        self.DeclarePeriodicDiscreteUpdateEvent(0.1, 0.0, self._update)
        self.DeclareStateOutputPort("distance", index)

    def _update(self, context, discrete_state):
        block = self._poses.Eval(context)[int(self._block.index())].translation()
        hand = self._target.Eval(context).translation()
        discrete_state.get_mutable_vector().SetAtIndex(0, float(np.linalg.norm(block - hand)))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint")
    parser.add_argument("--preset", default=None, help="use an UNTRAINED model of this preset (tiny, cpu) instead of the shipped checkpoint")
    parser.add_argument("--seconds", type=float, default=3.0)
    args = parser.parse_args()
    torch.set_num_threads(1)

    scenario = load_scenario()
    # 1. An extra object: a second green block, added to the scenario's model directives.
    scenario.directives.append(ModelDirective(add_model=AddModel(
        name="block_extra", file="package://trivla_drake_models/block_green.sdf",
        default_free_body_pose={"block": Transform(RigidTransform([0.55, -0.12, 0.0225]))})))
    # 2. The static camera moved to the robot's right, and 3. a top-down camera for the user.
    scenario.cameras["static_camera"].X_PB = Transform(
        RigidTransform(RollPitchYaw(np.radians([-125.0, 0.0, 35.0])), [0.9, -0.6, 0.6]))
    top = CameraConfig(name="top_camera", width=160, height=120, fps=5.0)
    top.X_PB = Transform(RigidTransform(RollPitchYaw(np.pi, 0.0, -np.pi / 2), [0.45, 0.0, 1.4]))
    scenario.cameras["top_camera"] = top

    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", make_station(scenario))
    policy = add_trivla_policy(builder, station, load_model(args.checkpoint, preset=args.preset))
    instruction = builder.AddNamedSystem("instruction", ConstantValueSource(AbstractValue.Make("lift the green block")))
    builder.Connect(instruction.get_output_port(), policy.GetInputPort("instruction"))
    plant = station.GetSubsystemByName("plant")
    extra = plant.GetBodyByName("block", plant.GetModelInstanceByName("block_extra"))
    watcher = builder.AddNamedSystem("hand_to_block", HandToBlockDistance(plant, extra))
    builder.Connect(station.GetOutputPort("plant.body_poses"), watcher.GetInputPort("body_poses"))
    builder.Connect(policy.GetOutputPort("ee_target"), watcher.GetInputPort("ee_target"))
    diagram = builder.Build()

    simulator = make_simulator(diagram, scenario)
    simulator.AdvanceTo(args.seconds)
    context = simulator.get_context()
    top_image = station.GetOutputPort("top_camera.rgb_image").Eval(station.GetMyContextFromRoot(context))
    distance = watcher.GetOutputPort("distance").Eval(watcher.GetMyContextFromRoot(context))[0]
    print(f"top camera: {top_image.width()}x{top_image.height()}; hand target to extra block: {distance:.3f} m")


if __name__ == "__main__":
    main()
