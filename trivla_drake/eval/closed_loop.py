"""The closed-loop TriVLA diagram: station + TriVLAPolicy + diff-IK (+ Meshcat drawings)."""

from __future__ import annotations

import time
from dataclasses import dataclass

from pydrake.common.value import AbstractValue
from pydrake.geometry import Meshcat
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

from trivla_drake.nn import TriVLA
from trivla_drake.station.scenario import Scenario, make_simulator, with_cameras_held_rarely
from trivla_drake.station.station import make_station
from trivla_drake.systems.policy_visualizer import PolicyMeshcatVisualizer
from trivla_drake.systems.policy_wiring import add_trivla_policy
from trivla_drake.systems.trivla_policy import PolicyRates, TriVLAPolicy


@dataclass
class ClosedLoop:
    """The built diagram and the handles a runner needs."""

    diagram: Diagram
    station: Diagram
    policy: TriVLAPolicy


def make_closed_loop(
    scenario: Scenario,
    model: TriVLA,
    *,
    rates: PolicyRates | None = None,
    instruction: str | None = None,
    meshcat: Meshcat | None = None,
    seed: int = 0,
    hold_camera_images: bool = False,
) -> ClosedLoop:
    """Build the closed loop. With `instruction` None the diagram exports an `instruction` input
    (fix it per episode); otherwise a constant source feeds it. The policy reads the cameras'
    `.rgb_image_now` ports; the held `.rgb_image` ports sample at the scenario's fps only with
    `hold_camera_images` (else at initialisation only, which saves about a fifth of the loop's time)."""
    if not hold_camera_images:
        scenario = with_cameras_held_rarely(scenario)
    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", make_station(scenario, meshcat=meshcat))
    policy = add_trivla_policy(builder, station, model, rates=rates, seed=seed, warn_tracking=False)
    if instruction is None:
        builder.ExportInput(policy.GetInputPort("instruction"), "instruction")
    else:
        source = builder.AddNamedSystem("instruction", ConstantValueSource(AbstractValue.Make(instruction)))
        builder.Connect(source.get_output_port(), policy.GetInputPort("instruction"))
    if meshcat is not None:
        drawer = builder.AddNamedSystem("policy_visualizer", PolicyMeshcatVisualizer(
            meshcat, horizon=model.config.policy.action_horizon))
        builder.Connect(policy.GetOutputPort("ee_target"), drawer.GetInputPort("ee_target"))
        builder.Connect(policy.GetOutputPort("action_chunk"), drawer.GetInputPort("action_chunk"))
    diagram = builder.Build()
    diagram.set_name("trivla_closed_loop")
    return ClosedLoop(diagram, station, policy)


def benchmark_closed_loop(scenario: Scenario, model: TriVLA, seconds: float = 3.0) -> dict:
    """Real-time factor of the full closed loop (both cameras, all of the model's systems)."""
    loop = make_closed_loop(scenario, model, instruction="put the red block in the bowl")
    simulator = make_simulator(loop.diagram, scenario)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(seconds)
    wall = time.perf_counter() - start
    policy_context = loop.policy.systems["policy"].GetMyContextFromRoot(simulator.get_context())
    return {
        "closed_loop_rtf": seconds / wall,
        "closed_loop_sim_seconds": seconds,
        "closed_loop_chunks": loop.policy.systems["policy"].slots(policy_context).count,
        "closed_loop_control_hz": loop.policy.systems["executor"].action_space.control_rate_hz,
    }
