"""The episode-start registry: where an episode's task starts. `run_episode(start=...)` resets the simulation to
the scene drawn from the episode's seed, then hands it to the start, which may change the scene and the hand before
the policy takes over (no start: the drawn scene and the start posture).

    @register_episode_start("name")
    def make_mine(**settings) -> EpisodeStart: ...

    run_episode(task, seed, policy, start=make_episode_start("chain_prelude", tasks=2))

Registered here: "chain_prelude", the oracle first completes other tasks of a chain (`collect --set prelude_tasks=K`,
`evaluate --set prelude=K`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from trivla_drake.eval.registry import Registry
from trivla_drake.tasks.chains import CHAIN_LENGTH, prelude_task
from trivla_drake.tasks.suite import TaskInstance, get_task

if TYPE_CHECKING:
    from trivla_drake.eval.env import TabletopEnv

EPISODE_STARTS = Registry("episode start")


@dataclass
class StartedEpisode:
    """Where an episode start left the simulation."""

    obs: dict  # the observation after the start
    # The episode's task drawn in the state the start left; None when the start failed (`reason` says why) and the
    # episode is a failure without a step.
    instance: TaskInstance | None
    # The tasks completed before the episode's, unrecorded, in order (`EpisodeResult.prelude`).
    prelude: tuple[str, ...] = ()
    reason: str = ""  # why the task cannot start ("" when it can)


class EpisodeStart(Protocol):
    """What `run_episode(start=...)` runs between the reset and the episode's task."""

    def begin(self, env: TabletopEnv, obs: dict, task_name: str, seed: int, paraphrase: bool) -> StartedEpisode:
        """Act on `env` from `obs` (just reset to the scene of the episode's `seed`), then draw `task_name`'s
        parameters and instruction (paraphrased or not) in the state left; its random draws derive from `seed`."""
        ...


def register_episode_start(name: str):
    """A decorator registering a factory of an `EpisodeStart` under `name`."""
    return EPISODE_STARTS.register(name)


def make_episode_start(name: str, **settings) -> EpisodeStart:
    """The episode start registered as `name`, made with `settings`; ValueError naming the registered ones, or the
    setting that cannot be."""
    return EPISODE_STARTS.make(name, **settings)


class ChainPrelude:
    """The oracle completes `tasks` other tasks of a chain (never a lift, which leaves a block in the hand), unrecorded
    and undisturbed, each drawn by `tasks.chains.prelude_task` (uniform over the tasks possible); the episode's task
    then starts where they left the scene and the hand, as the later tasks of a chain do. A prelude that fails, or
    leaves the task no way to start, fails the episode with the reason (it starts with "prelude")."""

    def __init__(self, tasks: int) -> None:
        if isinstance(tasks, bool) or not isinstance(tasks, int) or not 1 <= tasks < CHAIN_LENGTH:
            raise ValueError(f"chain_prelude: tasks must be an integer from 1 to {CHAIN_LENGTH - 1} (the tasks "
                             f"before the episode's in a chain of {CHAIN_LENGTH}), got {tasks!r}")
        from trivla_drake.tasks.oracle import OraclePolicy

        self.tasks = tasks
        self.policy = OraclePolicy()  # privileged: it plans from the simulator's ground truth

    def begin(self, env: TabletopEnv, obs: dict, task_name: str, seed: int, paraphrase: bool) -> StartedEpisode:
        from trivla_drake.eval.episode import derive_seed, run_unrecorded

        rng = np.random.default_rng(derive_seed(seed, "prelude"))
        done: list[str] = []
        for _ in range(self.tasks):
            step = prelude_task(env.scene(), rng, exclude={task_name, *done})
            if step is None:
                return StartedEpisode(obs, None, tuple(done), f"prelude: no task can run after {done or 'the start'}")
            sub, obs = run_unrecorded(env, obs, self.policy, step, int(rng.integers(2**31)))
            if not sub.success:
                return StartedEpisode(obs, None, tuple(done), f"prelude task {step.task}: {sub.reason}")
            done.append(step.task)
        task = get_task(task_name)
        candidates = task.candidates(env.scene())
        if not candidates:
            return StartedEpisode(obs, None, tuple(done), f"prelude: {task_name} cannot start after {', '.join(done)}")
        params = candidates[int(rng.integers(len(candidates)))]
        instance = TaskInstance(task_name, params, task.instruction(params, rng, paraphrase=paraphrase))
        return StartedEpisode(obs, instance, tuple(done))


register_episode_start("chain_prelude")(ChainPrelude)
