"""TriVLA closed loop: the Panda station driven by the three-system policy, in one Drake Diagram.

    python examples/closed_loop.py --seconds 5 --instruction "put the red block in the bowl"
"""

import argparse
import time

import torch
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

from trivla_drake import add_trivla_policy, load_model, load_scenario, make_simulator, make_station


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", help="TriVLA checkpoint (default: models/trivla_cpu)")
    parser.add_argument("--preset", default=None, help="use an UNTRAINED model of this preset (tiny, cpu) instead of the shipped checkpoint")
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--instruction", default="put the red block in the bowl")
    args = parser.parse_args()
    torch.set_num_threads(1)  # physics and rendering use the other core

    builder = DiagramBuilder()
    scenario = load_scenario()
    station = builder.AddNamedSystem("station", make_station(scenario))
    policy = add_trivla_policy(builder, station, load_model(args.checkpoint, preset=args.preset))
    instruction = builder.AddNamedSystem("instruction", ConstantValueSource(AbstractValue.Make(args.instruction)))
    builder.Connect(instruction.get_output_port(), policy.GetInputPort("instruction"))
    diagram = builder.Build()

    simulator = make_simulator(diagram, scenario)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(args.seconds)
    wall = time.perf_counter() - start
    context = policy.GetMyContextFromRoot(simulator.get_context())
    print(f"simulated {args.seconds:.1f} s in {wall:.1f} s (real-time factor {args.seconds / wall:.2f})")
    print("end-effector target [m]:", policy.GetOutputPort("ee_target").Eval(context).translation().round(3))
    # Each row one control step (1/36 s): the hand's translation [m] and rotation [rad] in the world frame, then
    # the gripper (+1 open, -1 closed).
    chunk = policy.GetOutputPort("action_chunk").Eval(context)
    print(f"latest action chunk ({chunk.shape[0]} steps x 7: dx dy dz [m], drx dry drz [rad], gripper):")
    print(chunk.round(3))


if __name__ == "__main__":
    main()
