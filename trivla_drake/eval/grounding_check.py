"""Does System 1's instruction grounding find the block an instruction names?

For each of a few unseen scenes of `lift_block`, the instruction is asked once per block colour
("pick up the red block", "... green ...", ...): the grounding's sub-goal (the next gripper event,
a grasp of the named block) should lie nearest to the block named, and close to it. A grounding
that ignores the colour word scores about 1/3, the share of one block among three, however close
it comes to *some* block (results/instruction_grounding).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from trivla_drake.tasks.scene import BLOCK_COLORS

CHECK_TASK = "lift_block"  # its first gripper event is the grasp of the block the instruction names


@dataclass
class GroundingCheck:
    """`hits` of `queries` sub-goals lie nearest (in x, y) to the block named; `median_error_m` is the
    median x-y distance to that block [m]; `chance` the hit rate of a colour-blind guess."""

    scenes: int
    queries: int
    hits: int
    median_error_m: float
    chance: float

    def to_dict(self) -> dict:
        return asdict(self)


def grounding_check(model, scenes: int = 10, seed: int = 1000) -> GroundingCheck:
    """Asks `model`'s grounding (a TriVLA with `policy.instruction_grounding`) for every block colour
    in `scenes` scenes of lift_block drawn from seeds `seed`, `seed` + 1, ... (1000 on: scenes the
    demonstrations, collected from seed 0, never showed)."""
    from trivla_drake.eval.episode import shared_env
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    if scenes < 1:
        raise ValueError(f"scenes must be >= 1, got {scenes}")
    if model.policy.grounding is None:
        raise ValueError("the model has no instruction grounding (policy.instruction_grounding is off): "
                         "train one with `train --stage policy --grounding-weight W`")
    env = shared_env(model.image_size)
    hits, errors = 0, []
    for k in range(scenes):
        spec, instance = sample_task_instance(get_task(CHECK_TASK), np.random.default_rng(seed + k), env.layout())
        named = instance.params[0]
        observation = env.reset(spec)
        scene = env.scene()
        for colour in BLOCK_COLORS:
            instruction = instance.instruction.replace(named, colour)
            subgoal = model.predict_subgoal(observation["static_rgb"], observation["wrist_rgb"], instruction)
            distance = {c: float(np.linalg.norm((subgoal - scene.block_position(c))[:2])) for c in BLOCK_COLORS}
            hits += min(distance, key=distance.get) == colour
            errors.append(distance[colour])
    return GroundingCheck(scenes=scenes, queries=len(errors), hits=hits,
                          median_error_m=float(np.median(errors)), chance=1.0 / len(BLOCK_COLORS))


def format_grounding_check(check: GroundingCheck) -> str:
    """One line for the terminal."""
    return (f"instruction grounding on {check.scenes} unseen lift_block scenes: the sub-goal is nearest the "
            f"named block in {check.hits}/{check.queries} queries ({check.hits / check.queries:.2f}; a colour-blind "
            f"guess {check.chance:.2f}), median {100 * check.median_error_m:.1f} cm from it")
