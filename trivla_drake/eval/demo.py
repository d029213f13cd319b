"""Closed-loop demo episodes: TriVLA as Drake systems (or the oracle) on tasks of the suite."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from pydrake.geometry import Meshcat

from trivla_drake.eval.closed_loop import ClosedLoop, make_closed_loop
from trivla_drake.eval.trivla_harness_policy import check_ensemble_decay, check_execute_steps
from trivla_drake.nn import TriVLA
from trivla_drake.station.scenario import Scenario, load_scenario, make_simulator
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.trivla_policy import PolicyRates
from trivla_drake.tasks.sim import StationHandles
from trivla_drake.tasks.suite import get_task, sample_task_instance

# How often the success predicate is checked [s of sim time].
CHECK_PERIOD_S = 0.25


@dataclass
class DemoReport:
    """What a demo run measured; `as_dict` is the --json output."""

    policy: str
    latency: str
    # TriVLA's chunk execution: replanning every this many control steps, and the ensemble decay.
    execute_steps: int | None = None
    ensemble_decay: float | None = None
    episodes: list[dict] = field(default_factory=list)
    sim_time: float = 0.0
    wall_time: float = 0.0
    played_actions: int = 0

    def count_run(self, wall_s: float, context, executor) -> None:
        """Adds one simulation's wall time [s], simulated time and played actions (the chunk executor's, in the
        root `context`)."""
        self.wall_time += wall_s
        self.sim_time += context.get_time()
        self.played_actions += executor.played_actions(executor.GetMyContextFromRoot(context))

    def as_dict(self) -> dict:
        successes = [e["success"] for e in self.episodes]
        return {
            "policy": self.policy,
            "latency": self.latency,
            "execute_steps": self.execute_steps,
            "ensemble_decay": self.ensemble_decay,
            "episodes": self.episodes,
            "success_rate": float(np.mean(successes)) if successes else 0.0,
            # Actions actually applied per simulated second (held ticks while waiting for a
            # chunk do not count): 36 Hz when inference keeps up, less with latency.
            "control_hz": self.played_actions / self.sim_time if self.sim_time else 0.0,
            "sim_time": self.sim_time,
            "wall_time": self.wall_time,
            "realtime_factor": self.sim_time / self.wall_time if self.wall_time else 0.0,
        }


def run_trivla_demo(
    model: TriVLA,
    task_name: str,
    *,
    episodes: int = 1,
    seed: int = 0,
    latency: LatencyModel | None = None,
    instruction: str | None = None,
    meshcat: Meshcat | None = None,
    scenario: Scenario | None = None,
    max_seconds: float | None = None,
    execute_steps: int | None = None,
    ensemble_decay: float | None = None,
    stage_offset_s: float = PolicyRates.stage_offset_s,
    on_episode_start=None,
    progress: bool = False,
) -> DemoReport:
    """Run `episodes` closed-loop episodes of `task_name` with TriVLA as Drake systems.

    Each episode draws its scene and instruction from `seed + i` (as the evaluation harness does);
    `instruction` overrides the task's text (success is still the task's predicate). With
    `execute_steps` K, Systems 1, 2 and 3 update every K control steps instead of once per chunk, and
    `ensemble_decay` averages the overlapping chunks (as `evaluate --set inference.execute_steps=K --set inference.ensemble_decay=M`).
    `stage_offset_s` is `PolicyRates.stage_offset_s` (0: the stages' simultaneous updates of before
    session 23, for comparison). `progress`: a bar on stderr with the successes so far.
    """
    task = get_task(task_name)
    demo = build_demo_loop(model, latency=latency, scenario=scenario, meshcat=meshcat, execute_steps=execute_steps,
                           ensemble_decay=ensemble_decay, stage_offset_s=stage_offset_s)
    loop, handles, executor = demo.loop, demo.handles, demo.executor
    limit = max_seconds if max_seconds is not None else task.max_steps * executor.action_space.dt
    report = demo.new_report()
    for episode in _episodes_with_bar(report, episodes, task_name, progress):
        rng = np.random.default_rng(seed + episode)
        simulator = make_simulator(loop.diagram, demo.scenario)
        context = simulator.get_mutable_context()
        spec, instance = sample_task_instance(task, rng, handles.layout(context))
        handles.apply(context, spec)
        text = instruction or instance.instruction
        loop.diagram.GetInputPort("instruction").FixValue(context, text)
        loop.policy.set_seed(context, int(rng.integers(2**31)))
        simulator.Initialize()
        if on_episode_start is not None:
            on_episode_start(episode)
        start = time.perf_counter()
        success, reason = advance_until_success(simulator, handles, task, instance.params, limit)
        report.count_run(time.perf_counter() - start, context, executor)
        report.episodes.append({
            "task": task_name, "instruction": text, "seed": seed + episode, "success": success,
            "sim_time": context.get_time(), "reason": reason,
        })
    return report


@dataclass
class DemoLoop:
    """The closed loop a demo runs, with the settings its report records."""

    loop: ClosedLoop
    handles: StationHandles
    scenario: Scenario
    latency: LatencyModel
    execute_steps: int
    ensemble_decay: float | None

    @property
    def executor(self):
        return self.loop.policy.systems["executor"]

    def new_report(self, kind: type[DemoReport] = DemoReport) -> DemoReport:
        """An empty report of `kind` (a DemoReport or a subclass) with this loop's settings."""
        latency = self.latency.mode if self.latency.mode != "fixed" else f"{self.latency.seconds}s"
        return kind(policy="trivla", latency=latency, execute_steps=self.execute_steps,
                    ensemble_decay=self.ensemble_decay)


def build_demo_loop(
    model: TriVLA,
    *,
    latency: LatencyModel | None = None,
    scenario: Scenario | None = None,
    meshcat: Meshcat | None = None,
    execute_steps: int | None = None,
    ensemble_decay: float | None = None,
    stage_offset_s: float = PolicyRates.stage_offset_s,
) -> DemoLoop:
    """The closed loop of `make_closed_loop` with the demo's chunk execution (`execute_steps`, `ensemble_decay`:
    ValueError naming the field when out of range) and its station handles."""
    latency = latency or LatencyModel()
    horizon = int(model.config.policy.action_horizon)
    steps = horizon if execute_steps is None else check_execute_steps(execute_steps, horizon, "execute_steps")
    decay = None if ensemble_decay is None else check_ensemble_decay(ensemble_decay, "ensemble_decay")
    rates = dataclasses.replace(PolicyRates.replanning_every(steps, ensemble_decay=decay, latency=latency),
                                stage_offset_s=stage_offset_s)
    scenario = scenario or load_scenario()
    loop = make_closed_loop(scenario, model, rates=rates, meshcat=meshcat)
    return DemoLoop(loop, StationHandles(loop.station), scenario, latency, steps, decay)


def advance_until_success(simulator, handles: StationHandles, task, params, until: float) -> tuple[bool, str]:
    """Advances `simulator` to sim time `until` [s], checking `task`'s predicate (against the scene as it is now)
    every CHECK_PERIOD_S; returns (success, why not: "" on success). A failed simulation is a failure with its
    message, not an exception."""
    context = simulator.get_mutable_context()
    initial = handles.read(context)
    try:
        while context.get_time() < until - 1e-9:
            simulator.AdvanceTo(min(until, context.get_time() + CHECK_PERIOD_S))
            if task.success(params, initial, handles.read(context)):
                return True, ""
    except RuntimeError as error:  # a failed simulation is this episode's failure
        return False, f"simulation failed: {error}"
    return False, "timeout"


def _episodes_with_bar(report: DemoReport, episodes: int, task_name: str, progress: bool):
    """range(episodes), with a bar that shows `report`'s successes so far."""
    return counted_with_bar(episodes, f"demo {task_name}", "ep", progress, lambda: {
        "success": f"{sum(e['success'] for e in report.episodes)}/{len(report.episodes)}"})


def counted_with_bar(count: int, description: str, unit: str, progress: bool, postfix):
    """range(count), with a tqdm bar on stderr (when `progress`) showing `postfix()` (a dict) after each item."""
    from tqdm import tqdm

    with tqdm(total=count, desc=description, unit=unit, disable=not progress) as bar:
        for index in range(count):
            yield index
            bar.set_postfix(postfix(), refresh=False)
            bar.update(1)


def run_oracle_demo(task_name: str, *, episodes: int = 1, seed: int = 0, progress: bool = False) -> DemoReport:
    """The scripted oracle on the same episodes (through the harness's action interface)."""
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    task = get_task(task_name)
    report = DemoReport(policy="oracle", latency="zero")
    dt = 1.0 / 36.0
    for episode in _episodes_with_bar(report, episodes, task_name, progress):
        start = time.perf_counter()
        result = run_episode(task_name, seed + episode, OraclePolicy(), max_steps=task.max_steps)
        report.wall_time += time.perf_counter() - start
        report.sim_time += result.steps * dt
        report.played_actions += result.steps
        report.episodes.append({
            "task": task_name, "instruction": result.instruction, "seed": seed + episode,
            "success": bool(result.success), "sim_time": result.steps * dt, "reason": result.reason or "",
        })
    return report
