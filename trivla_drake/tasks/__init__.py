"""trivla_drake.tasks: the language-conditioned task suite, success predicates, the oracle, chains.

    from trivla_drake.tasks import TASKS, get_task
    task = get_task("open_drawer")
    task.templates, task.paraphrases          # training instructions / held-out paraphrases
    task.candidates(scene)                    # parameter choices whose preconditions hold
    task.success(params, initial, current)    # predicate on SceneState snapshots
"""

from trivla_drake.tasks.scene import BLOCK_COLORS, Layout, SceneSpec, SceneState, sample_scene, scene_from_spec
from trivla_drake.tasks.suite import (
    TASK_NAMES,
    TASKS,
    Task,
    TaskInstance,
    UnknownTaskError,
    get_task,
    parse_task_list,
    sample_task_instance,
)

__all__ = [
    "BLOCK_COLORS",
    "Layout",
    "SceneSpec",
    "SceneState",
    "TASKS",
    "TASK_NAMES",
    "Task",
    "TaskInstance",
    "UnknownTaskError",
    "get_task",
    "parse_task_list",
    "sample_scene",
    "sample_task_instance",
    "scene_from_spec",
]
