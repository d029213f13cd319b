"""Run the station closed loop with the diff-IK following a scripted end-effector path."""

from __future__ import annotations

import time
from dataclasses import dataclass

from pydrake.geometry import Meshcat
from pydrake.systems.framework import Diagram, DiagramBuilder

from trivla_drake.station.meshcat_setup import save_static_html
from trivla_drake.station.scenario import Scenario, make_simulator
from trivla_drake.station.station import make_station
from trivla_drake.systems.diffik_system import DifferentialIKSystem
from trivla_drake.systems.scripted_path import CirclePath, ScriptedEndEffectorPath


@dataclass
class RunTiming:
    """How fast a simulation ran: simulated seconds, wall-clock seconds and their ratio."""

    sim_time: float
    wall_time: float

    @property
    def realtime_factor(self) -> float:
        return self.sim_time / self.wall_time if self.wall_time > 0 else float("inf")

    def as_dict(self) -> dict:
        return {"sim_time": self.sim_time, "wall_time": self.wall_time, "realtime_factor": self.realtime_factor}


def make_scripted_diagram(
    scenario: Scenario, *, meshcat: Meshcat | None = None, path: CirclePath | None = None
) -> Diagram:
    """Station + DifferentialIKSystem + ScriptedEndEffectorPath, wired closed loop."""
    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", make_station(scenario, meshcat=meshcat))
    diffik = builder.AddNamedSystem("diffik", DifferentialIKSystem(warn_tracking=False))
    script = builder.AddNamedSystem("scripted_path", ScriptedEndEffectorPath(path))
    builder.Connect(script.GetOutputPort("ee_target"), diffik.GetInputPort("ee_target"))
    builder.Connect(station.GetOutputPort("panda.state"), diffik.GetInputPort("robot_state"))
    builder.Connect(diffik.GetOutputPort("position_setpoint"), station.GetInputPort("panda.position"))
    builder.Connect(script.GetOutputPort("gripper_width"), station.GetInputPort("panda.gripper_width"))
    diagram = builder.Build()
    diagram.set_name("scripted_station")
    return diagram


def run_scripted(
    scenario: Scenario,
    seconds: float,
    *,
    meshcat: Meshcat | None = None,
    record_html: str | None = None,
) -> RunTiming:
    """Simulate `seconds` of the scripted run; optionally record it to a self-contained HTML page."""
    if not seconds > 0:
        raise ValueError(f"seconds must be positive, got {seconds}")
    if record_html is not None and meshcat is None:
        raise ValueError("record_html needs a meshcat to record from")
    diagram = make_scripted_diagram(scenario, meshcat=meshcat)
    simulator = make_simulator(diagram, scenario)
    simulator.Initialize()
    if record_html is not None:
        meshcat.StartRecording(frames_per_second=30.0)
    start = time.perf_counter()
    simulator.AdvanceTo(seconds)
    wall = time.perf_counter() - start
    if record_html is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
        save_static_html(meshcat, record_html)
    return RunTiming(sim_time=seconds, wall_time=wall)
