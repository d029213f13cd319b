"""5-task chains with TriVLA as Drake systems: one simulation per chain, the instruction input changed when a task is
done, as a user's diagram would drive the policy through a long-horizon job.

Chain j draws its scene and tasks from `derive_seed(seed, "chain", j)`, as `evaluate --chains`'s chain j does, so
both start from the same scene and the same first task; a later task is drawn, as there, from the tasks whose
preconditions hold in the scene the one before left (the draws can part where the two runs leave other scenes).
Each task gets its own step budget (`max_steps` control steps, or `max_seconds`), a task whose predicate already holds
when it is drawn ends the chain uncounted (as in the harness), and the first failure ends the chain.

The difference from the harness: there the policy starts each task afresh (its queued chunk dropped). Here the
policy's systems keep running through the switch, reading the new instruction at their next update, so up to one
chunk planned for the task before is still played, as it would be in any diagram that streams instructions.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydrake.geometry import Meshcat

from trivla_drake.eval.demo import DemoReport, advance_until_success, build_demo_loop, counted_with_bar
from trivla_drake.eval.episode import derive_seed
from trivla_drake.eval.evaluate import summarize_chains
from trivla_drake.nn import TriVLA
from trivla_drake.station.scenario import Scenario, make_simulator
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.trivla_policy import PolicyRates
from trivla_drake.tasks.chains import CHAIN_LENGTH, next_chain_task, sample_chain_scene
from trivla_drake.tasks.suite import get_task


@dataclass
class ChainDemoReport(DemoReport):
    """A `DemoReport` of chains: each with its tasks (`subtasks`), in order; no episodes of their own."""

    chains: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        result = super().as_dict()
        del result["episodes"]  # the chains' subtasks are the episodes
        del result["success_rate"]  # the tasks after a failure are never tried: Avg. Len is the measure
        result["chain_runs"] = self.chains
        if self.chains:
            result.update(summarize_chains(self.chains))
        return result


def run_trivla_chain_demo(
    model: TriVLA,
    *,
    chains: int = 1,
    seed: int = 0,
    length: int = CHAIN_LENGTH,
    latency: LatencyModel | None = None,
    meshcat: Meshcat | None = None,
    scenario: Scenario | None = None,
    max_seconds: float | None = None,
    execute_steps: int | None = None,
    ensemble_decay: float | None = None,
    stage_offset_s: float = PolicyRates.stage_offset_s,
    on_task_start=None,
    progress: bool = False,
) -> ChainDemoReport:
    """Run `chains` chains of `length` tasks with TriVLA as Drake systems (see the module docstring).
    `max_seconds` bounds each task [s of sim time] (default: the task's own limit); `on_task_start(chain, k,
    instance, context)` is called as the k-th task (0-based) is handed to the policy (`context`: the root context,
    its instruction input already set)."""
    if isinstance(chains, bool) or not isinstance(chains, (int, np.integer)) or chains < 1:
        raise ValueError(f"chains must be an integer >= 1, got {chains!r}")
    if not 1 <= length <= CHAIN_LENGTH:
        raise ValueError(f"length must be 1 to {CHAIN_LENGTH} tasks, got {length!r}")
    demo = build_demo_loop(model, latency=latency, scenario=scenario, meshcat=meshcat, execute_steps=execute_steps,
                           ensemble_decay=ensemble_decay, stage_offset_s=stage_offset_s)
    loop, handles, executor = demo.loop, demo.handles, demo.executor
    report = demo.new_report(ChainDemoReport)
    instruction_port = loop.diagram.GetInputPort("instruction")
    for index in _chains_with_bar(report, chains, progress):
        chain_seed = derive_seed(seed, "chain", index)
        rng = np.random.default_rng(chain_seed)
        simulator = make_simulator(loop.diagram, demo.scenario)
        context = simulator.get_mutable_context()
        handles.apply(context, sample_chain_scene(rng, handles.layout(context)))
        chain = {"seed": chain_seed, "completed": 0, "reason": "", "subtasks": []}
        used: set[str] = set()
        start = time.perf_counter()
        for k in range(length):
            instance = next_chain_task(handles.read(context), rng, used)
            if instance is None:
                chain["reason"] = "no task's preconditions hold (chain generator)"
                break
            used.add(instance.task)
            task = get_task(instance.task)
            instruction_port.FixValue(context, instance.instruction)
            loop.policy.set_seed(context, int(rng.integers(2**31)))
            if k == 0:
                simulator.Initialize()
            if on_task_start is not None:
                on_task_start(index, k, instance, context)
            began = context.get_time()
            budget = max_seconds if max_seconds is not None else task.max_steps * executor.action_space.dt
            scene = handles.read(context)
            if task.success(instance.params, scene, scene):
                success, reason = False, "predicate already true at the start (not counted as a success)"
            else:
                success, reason = advance_until_success(simulator, handles, task, instance.params, began + budget)
            subtask = {"task": instance.task, "instruction": instance.instruction, "seed": chain_seed,
                       "success": success, "sim_time": context.get_time() - began, "reason": reason}
            chain["subtasks"].append(subtask)
            if not success:
                chain["reason"] = f"{instance.task}: {reason}"
                break
            chain["completed"] += 1
        report.count_run(time.perf_counter() - start, context, executor)
        report.chains.append(chain)
    return report


def _chains_with_bar(report: ChainDemoReport, chains: int, progress: bool):
    """range(chains), with a bar that shows the Avg. Len so far."""
    return counted_with_bar(chains, "demo chains", "chain", progress,
                            lambda: {"avg_len": f"{np.mean([c['completed'] for c in report.chains]):.2f}"})
