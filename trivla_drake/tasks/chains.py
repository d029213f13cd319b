"""CALVIN-style chains: five tasks in a row from one initial state, each chosen only if its
preconditions hold in the state the previous task left behind; and the preludes of collected
demonstrations that start where a chain's earlier tasks leave the scene."""

from __future__ import annotations

import copy

import numpy as np

from trivla_drake.tasks.scene import Layout, SceneSpec, SceneState, sample_scene
from trivla_drake.tasks.suite import TASK_NAMES, TASKS, TaskInstance

CHAIN_LENGTH = 5
# Tasks that leave a block in the hand, and the tasks that can follow them.
NEEDS_FOLLOW_UP = {"lift_block": ("place_in_bowl", "stack_block")}


def sample_chain_scene(rng: np.random.Generator, layout: Layout) -> SceneSpec:
    """A chain's initial state: random blocks (sometimes stacked), drawer and lamp."""
    return sample_scene(rng, layout, stack=bool(rng.random() < 0.3))


def lifted_scene(scene: SceneState, color: str) -> SceneState:
    """`scene` as it would look with `color` held 15 cm above the table."""
    lifted = copy.copy(scene)
    lifted.blocks = dict(scene.blocks)
    block = scene.blocks[color].copy()
    block[2, 3] = 0.15
    lifted.blocks[color] = block
    tcp = scene.tcp.copy()
    tcp[:3, 3] = block[:3, 3]
    lifted.tcp = tcp
    lifted.finger_width = 0.045
    return lifted


def chain_options(scene: SceneState, used: set[str]) -> dict[str, list[tuple]]:
    """Task name -> parameter choices possible now, preferring tasks not yet used in the chain."""

    def options(allow_used: bool) -> dict[str, list[tuple]]:
        out: dict[str, list[tuple]] = {}
        for name in TASK_NAMES:
            if name in used and not allow_used:
                continue
            params = TASKS[name].candidates(scene)
            if name in NEEDS_FOLLOW_UP:
                follow = NEEDS_FOLLOW_UP[name]
                params = [p for p in params if any(TASKS[f].candidates(lifted_scene(scene, p[0])) for f in follow)]
            if params:
                out[name] = params
        return out

    return options(False) or options(True)


def next_chain_task(
    scene: SceneState, rng: np.random.Generator, used: set[str], *, paraphrase: bool = False
) -> TaskInstance | None:
    """The next task of a chain (uniform over possible tasks, then over their parameters), or None."""
    return _draw(chain_options(scene, used), rng, paraphrase)


def _draw(options: dict[str, list[tuple]], rng: np.random.Generator, paraphrase: bool) -> TaskInstance | None:
    """A task uniform over `options`' names, then its parameters uniform over theirs (None if empty)."""
    if not options:
        return None
    names = sorted(options)
    name = names[int(rng.integers(len(names)))]
    params = options[name][int(rng.integers(len(options[name])))]
    return TaskInstance(name, params, TASKS[name].instruction(params, rng, paraphrase=paraphrase))


# Tasks a prelude (the episode start "chain_prelude", eval/episode_starts.py) never runs: a lift leaves the block in the
# hand, and the task after it in a chain is then always place or stack.
_NOT_IN_PRELUDE = frozenset({"lift_block"})


def prelude_task(scene: SceneState, rng: np.random.Generator, exclude: set[str]) -> TaskInstance | None:
    """One task of a chain's beginning before a recorded task (uniform over the tasks possible in
    `scene` that are not in `exclude` and leave the hand empty, then over their parameters), or None."""
    options = {name: params for name, params in chain_options(scene, set()).items()
               if name not in exclude and name not in _NOT_IN_PRELUDE}
    return _draw(options, rng, paraphrase=False)
