"""Diagnostic (session 46): do the lamp presses fail after a task that leaves the hand turned?

python results/grounding_scenes/lamp_after_prelude.py OUT.json [EPISODES (3)] [CHECKPOINT (models/trivla_cpu)]

Every lamp failure of the shipped model's 80 chains came after a rotate or an unstack (`chain_positions.md`), and the
oracle presses at one fixed yaw (`tasks/motions.py`, `press`). Here turn on and turn off the light run after a
one-task prelude chosen on purpose (the oracle does it, unrecorded, as `evaluate --prelude 1` does): a rotation
(which leaves the hand turned with the block) or a drawer task (whose handle grasp leaves the hand at one yaw). For
each, the hand's yaw off the press's yaw when the policy starts (modulo a half turn: the two fingers look alike) and
whether the light was switched. Episode seeds derive from 3000; a prelude that cannot run is drawn again."""

import json
import math
import statistics
import sys

import torch

from trivla_drake.eval import episode as ep
from trivla_drake.eval.policies import load_policy
from trivla_drake.tasks.scene import hand_yaw
from trivla_drake.tasks.suite import TASKS, TaskInstance

PRELUDES = ("rotate_block_left", "rotate_block_right", "open_drawer", "close_drawer")
LAMP_TASKS = ("turn_on_light", "turn_off_light")
REDRAWS = 5


class _YawAtStart:
    """The policy, noting the hand's yaw off the press's (degrees, in [0, 90]) at each episode's first chunk."""

    def __init__(self, inner):
        self.inner, self.yaw_off = inner, None

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def reset(self, instruction, seed):
        self.yaw_off = None
        return self.inner.reset(instruction, seed)

    def act(self, observation):
        if self.yaw_off is None:
            off = math.remainder(hand_yaw(observation["tcp_pose"]), math.pi)  # press yaw 0, fingers symmetric
            self.yaw_off = abs(math.degrees(off))
        return self.inner.act(observation)


def forced_prelude(name: str):
    """A `run_episode(prelude_draw=...)` that always draws task `name` (None where it cannot run)."""

    def draw(scene, rng, exclude):
        params = TASKS[name].candidates(scene)
        if name in exclude or not params:
            return None
        chosen = params[int(rng.integers(len(params)))]
        return TaskInstance(name, chosen, TASKS[name].instruction(chosen, rng))

    return draw


def run(policy, oracle, prelude: str, lamp: str, index: int) -> dict:
    for redraw in range(REDRAWS + 1):
        result = ep.run_episode(lamp, ep.derive_seed(3000, lamp, prelude, index, redraw), policy, image_size=224,
                                prelude=1, prelude_policy=oracle, prelude_draw=forced_prelude(prelude))
        if not result.reason.startswith("prelude"):
            break
    return {"prelude": prelude, "task": lamp, "index": index, "success": result.success, "reason": result.reason,
            "yaw_off_deg": policy.yaw_off, "ran_prelude": list(result.prelude)}


def table(rows: list[dict]) -> str:
    lines = ["| prelude | turn on | turn off | hand's yaw off the press's at the start, median [deg] |",
             "| --- | --- | --- | --- |"]
    for prelude in PRELUDES:
        mine = [r for r in rows if r["prelude"] == prelude and r["ran_prelude"]]
        cells = []
        for lamp in LAMP_TASKS:
            these = [r for r in mine if r["task"] == lamp]
            cells.append(f"{sum(r['success'] for r in these)} / {len(these)}")
        yaws = [r["yaw_off_deg"] for r in mine if r["yaw_off_deg"] is not None]
        lines.append(f"| {prelude} | {cells[0]} | {cells[1]} | {statistics.median(yaws):.0f} |" if yaws
                     else f"| {prelude} | {cells[0]} | {cells[1]} | - |")
    return "\n".join(lines)


def main(argv: list[str]) -> str:
    if not 1 <= len(argv) <= 3:
        sys.exit(__doc__)
    episodes = int(argv[1]) if len(argv) > 1 else 3
    torch.set_num_threads(1)
    policy = _YawAtStart(load_policy(argv[2] if len(argv) > 2 else "trivla"))
    oracle = load_policy("oracle")
    rows = [run(policy, oracle, prelude, lamp, i) for prelude in PRELUDES for lamp in LAMP_TASKS for i in range(episodes)]
    with open(argv[0], "w") as out:
        json.dump(rows, out, indent=1)
    return table(rows)


if __name__ == "__main__":
    print(main(sys.argv[1:]))
