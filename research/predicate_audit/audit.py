"""Do the suite's success predicates count outcomes a person would not? (session 66)

A review found three ways a predicate can say yes too early or too easily:
- stack_block: the top block counts as stacked with its centre up to 3 cm off the base's, past the base's edge
  (half a block, 2.25 cm), and the episode ends at the first step the predicate holds, so a block let go over the
  edge scores before it topples;
- unstack_block: the top block needs only to lie on the table on any face, so a knocked-over tower scores;
- rotate_block_left/right: the block may also be shoved across the table.

The other tasks are audited the same way (their stricter reading is their own predicate).

This script runs `evaluate`'s episodes (the same seeds, scenes, instructions and policy seeds) and, at each success,
lets the hand hold still (`HOLD_STEPS` control steps of zero motion, the gripper as last commanded) and asks again, with the
task's own predicate and a stricter one. It changes no predicate: it measures how many reported successes the
stricter reading would keep, so the reported figures can be read with that in mind.

    python results/predicate_audit/audit.py --policy trivla --seeds 1000-1005 --episodes 2 --out results/predicate_audit/shipped.json
"""

from __future__ import annotations

import argparse
import json
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from trivla_drake.eval.episode import derive_seed, hold_still, run_episode, shared_env
from trivla_drake.eval.evaluate import _policy
from trivla_drake.tasks.scene import BLOCK_HALF, fold_quarter_turn
from trivla_drake.tasks.suite import TASKS

# Half a second at 36 Hz: long enough for a block let go past its base's edge to tip.
HOLD_STEPS = 18
AUDITED = ("stack_block", "unstack_block", "rotate_block_left", "rotate_block_right")
# The stricter readings.
STACK_MAX_OFFSET = BLOCK_HALF  # the top's centre over the base (its centre of mass inside the base's face)
UNSTACK_BASE_MAX_SHIFT = 0.02  # [m] the base stays where it stood, upright on the table
ROTATE_MAX_SHIFT = 0.03  # [m] a rotation in place, not a shove


def strict_success(task: str, params: tuple, initial, current) -> bool:
    """The task's own predicate and the stricter reading above."""
    if not TASKS[task].success(params, initial, current):
        return False
    if task == "stack_block":
        top, base = params
        offset = current.block_position(top) - current.block_position(base)
        return bool(np.hypot(offset[0], offset[1]) <= STACK_MAX_OFFSET)
    if task == "unstack_block":
        top, base = params
        shift = current.block_position(base)[:2] - initial.block_position(base)[:2]
        return bool(current.on_table(base) and current.is_upright(base) and np.linalg.norm(shift) <= UNSTACK_BASE_MAX_SHIFT
                    and current.base_of(top) is None)
    if task.startswith("rotate_block"):
        shift = current.block_position(params[0])[:2] - initial.block_position(params[0])[:2]
        return bool(np.linalg.norm(shift) <= ROTATE_MAX_SHIFT)
    return True


@contextmanager
def _first_scenes(task: str):
    """Records the scene each call of `task`'s predicate compared against (`initial`) while the block runs."""
    seen: dict = {}
    real = TASKS[task].success

    def recording(params, initial, current):
        seen["initial"] = initial
        return real(params, initial, current)

    TASKS[task].success = recording
    try:
        yield seen
    finally:
        TASKS[task].success = real


def audit_episode(task: str, seed: int, policy) -> dict:
    """One of `evaluate`'s episodes; at a success, the strict reading then, and both readings after the hold."""
    with _first_scenes(task) as seen:
        result = run_episode(task, seed, policy)
    row = {"task": task, "seed": seed, "success": bool(result.success), "steps": result.steps}
    if not result.success:
        return row
    env = shared_env(224 if policy.uses_images else None)
    initial, params = seen["initial"], tuple(result.params)
    at_success = env.scene()
    row["strict_at_success"] = strict_success(task, params, initial, at_success)
    hold_still(env, HOLD_STEPS)  # the hand keeps its last gripper command (holding a lifted block, or letting go)
    after = env.scene()
    row["success_after_hold"] = bool(TASKS[task].success(params, initial, after))
    row["strict_after_hold"] = strict_success(task, params, initial, after)
    if params and params[0] in after.blocks:  # a block task
        row["at_success"] = describe(params[0], initial, at_success)
        row["after_hold"] = describe(params[0], initial, after)
    return row


def describe(color: str, initial, scene) -> dict:
    """What a person would look at: the block's height, tilt, turn and shift since the start, the hand's opening
    and its distance from the block."""
    block = scene.blocks[color]
    tilt = float(np.degrees(np.arccos(np.clip(np.max(np.abs(block[2, :3])), -1.0, 1.0))))
    turn = float(np.degrees(fold_quarter_turn(scene.block_yaw(color) - initial.block_yaw(color))))
    shift = scene.block_position(color)[:2] - initial.block_position(color)[:2]
    return {"z_m": round(float(block[2, 3]), 4), "tilt_deg": round(tilt, 1), "turn_deg": round(turn, 1),
            "shift_m": round(float(np.linalg.norm(shift)), 4), "finger_width_m": round(float(scene.finger_width), 4),
            "hand_to_block_m": round(float(np.linalg.norm(scene.block_position(color) - scene.tcp[:3, 3])), 4)}


def summarize(rows: list[dict]) -> dict:
    """Per task: episodes, successes, and how many of those each later reading keeps."""
    out = {}
    for task in sorted({r["task"] for r in rows}):
        mine = [r for r in rows if r["task"] == task]
        won = [r for r in mine if r["success"]]
        out[task] = {"episodes": len(mine), "successes": len(won),
                     **{key: sum(r[key] for r in won) for key in
                        ("strict_at_success", "success_after_hold", "strict_after_hold")}}
    return out


def format_markdown(summary: dict) -> str:
    lines = [f"| task | successes / episodes | strict at the success | still after {HOLD_STEPS} held steps | "
             "strict after the hold |", "| --- | --- | --- | --- | --- |"]
    for task, s in summary.items():
        lines.append(f"| {task} | {s['successes']} / {s['episodes']} | {s['strict_at_success']} | "
                     f"{s['success_after_hold']} | {s['strict_after_hold']} |")
    return "\n".join(lines)


def _seeds(text: str) -> list[int]:
    if "-" in text:
        first, last = (int(x) for x in text.split("-"))
        return list(range(first, last + 1))
    return [int(x) for x in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default="trivla", help="oracle, trivla or a checkpoint folder")
    parser.add_argument("--tasks", default=",".join(AUDITED))
    parser.add_argument("--seeds", default="1000-1005", help="evaluate's base seeds: 1000-1005 or 1000,1001")
    parser.add_argument("--episodes", type=int, default=2, help="episodes per task and seed")
    parser.add_argument("--out", default=None, help="JSON file for the rows and the summary")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    policy = _policy(args.policy)
    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
    for task in tasks:
        if task not in TASKS:
            parser.error(f"--tasks: unknown task {task!r}")
    rows, start = [], time.perf_counter()
    for base in _seeds(args.seeds):
        for task in tasks:
            for i in range(args.episodes):
                rows.append(audit_episode(task, derive_seed(base, task, i), policy))
    summary = summarize(rows)
    print(format_markdown(summary))
    print(f"\n{len(rows)} episodes in {time.perf_counter() - start:.0f} s")
    if args.out:
        Path(args.out).write_text(json.dumps({"policy": args.policy, "seeds": args.seeds, "episodes": args.episodes,
                                              "hold_steps": HOLD_STEPS, "summary": summary, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
