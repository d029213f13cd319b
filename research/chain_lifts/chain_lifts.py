"""Why do the grasp tasks fail in chains? Each lift (or place, stack, unstack) of the `--home-first` chains, traced.

    python results/chain_lifts/chain_lifts.py CHECKPOINT OUT.json [--task T] [--budget-extra N] [--single-seeds A-B]

In the 80 chains of seeds 1003-1006 with `--home-first` (`../prelude_reset/settled_home_chains20_*.json`) a lift
succeeds in 13 of 32 tries (2 of 10 as a chain's third task), against 26 of 36 single lifts from the start
posture (seeds 1000-1017). This reruns every chain of those files that tries a lift (`--task`: or place in bowl,
stack, unstack; each starts with a grasp of the block its instruction names first), up to and including that
task (`run_chain(length=its position)`: the same scene, tasks, instructions and policy seeds). The stored files
were made on another machine, whose CPU rounds some of the policy's float operations differently, and a closed
loop turns such differences into other trajectories: a chain may now fail before its lift (`reached` false) or
its lift go the other way, so the figures compared are the ones this run makes, on one machine. A recorder
between `HomeFirst` and the policy sees every chunk the policy plans (none during the homing) and records, per
try:

- where it is in the chain and what came before, the homing's steps (a lift's budget is 360 steps);
- the named block at the task's start: on the table or on another block, its yaw against the hand's, how far
  the nearest other block is, whether the drawer is open and the lamp on;
- per chunk the policy plans: the tool-centre point, the block, whether it is held, whether the chunk closes;
  from them the first chunk that commands the gripper closed (its x-y distance to the block and its height),
  how often it closes, whether the block was ever held and how high it got.

Every try runs `--budget-extra N` (default 108, the homing's most) steps beyond its task's budget. Up to the
budget's last step the trajectory does not depend on the budget, so one run gives both: `success` (within the
budget, as `evaluate` counts it) and `success_extended` (within N more): a try that only needed the steps the
homing took succeeds in the second. `--single-seeds A-B` also traces the task's single episodes of `evaluate
--episodes 2 --seed S` for S in A..B (no homing, the start posture) the same way: the reference the chain tries
are compared with.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
# The tasks that start with a grasp of the block their instruction names first.
TRACED_TASKS = ("lift_block", "place_in_bowl", "stack_block", "unstack_block")
CHAIN_FILES = sorted((HERE.parent / "prelude_reset").glob("settled_home_chains20_seed*.json"))


class ChunkRecorder:
    """Between HomeFirst and the policy: records, per chunk the policy plans, the hand and the block the
    instruction names (read from the simulator, a diagnostic's privilege the policy does not get)."""

    def __init__(self, policy, env):
        self.policy, self.env = policy, env
        self.name, self.uses_images, self.privileged = policy.name, policy.uses_images, policy.privileged
        self.tasks: list[dict] = []

    def reset(self, instruction: str, seed: int) -> None:
        from trivla_drake.tasks.scene import BLOCK_COLORS

        named = [w for w in instruction.split() if w in BLOCK_COLORS]
        color = named[0] if named else None  # the block to pick up is named first (lift, place, stack, unstack)
        self.tasks.append({"instruction": instruction, "color": color, "start_step": self.env.step_index,
                           "start": start_scene(self.env.scene(), color), "chunks": []})
        self.policy.reset(instruction, seed)

    def act(self, observation: dict) -> np.ndarray:
        from trivla_drake.eval.policies import as_action_rows

        record = self.tasks[-1]
        rows = as_action_rows(self.policy.act(observation))  # (k, 7): the oracle gives one row, TriVLA a chunk
        scene = self.env.scene()
        color = record["color"]
        record["chunks"].append({
            "step": self.env.step_index - record["start_step"],
            "tcp": [float(v) for v in observation["tcp_pose"][:3, 3]],
            "block": None if color is None else [float(v) for v in scene.block_position(color)],
            "held": bool(color is not None and scene.is_held(color)),
            "closes": bool(np.any(rows[:, 6] <= 0)),
        })
        return rows


def start_scene(scene, color) -> dict:
    """The scene a task starts in, as far as a grasp of `color` is concerned."""
    from trivla_drake.tasks.scene import hand_yaw, yaw_to_faces_deg

    out = {"drawer_opening": float(scene.drawer_opening), "lamp_on": bool(scene.lamp_on),
           "tcp": [float(v) for v in scene.tcp[:3, 3]]}
    if color is not None:
        p = scene.block_position(color)
        others = [np.linalg.norm(scene.block_position(c)[:2] - p[:2]) for c in scene.blocks if c != color]
        out.update(block=[float(v) for v in p], base=scene.base_of(color), in_bowl=bool(scene.in_bowl(color)),
                   yaw_to_hand_deg=float(yaw_to_faces_deg(hand_yaw(scene.tcp), scene.block_yaw(color))),
                   nearest_other_m=float(min(others)))
    return out


def grasp_trace(record: dict) -> dict:
    """The per-chunk record of one try, summarised."""
    chunks, out = record["chunks"], {"homing_steps": None, "first_close": None}
    if chunks:
        out["homing_steps"] = chunks[0]["step"]
    closing = [c for c in chunks if c["closes"]]
    out["chunks_closed"] = len(closing)
    out["closes"] = sum(1 for a, b in zip(chunks, chunks[1:]) if b["closes"] and not a["closes"]) + int(
        bool(chunks) and chunks[0]["closes"])
    if closing:
        c = closing[0]
        out["first_close"] = {"step": c["step"], "xy_to_block_cm": 100 * float(np.hypot(
            c["tcp"][0] - c["block"][0], c["tcp"][1] - c["block"][1])), "tcp_z_cm": 100 * c["tcp"][2]}
    blocks = [c["block"][2] for c in chunks if c["block"] is not None]
    out["ever_held"] = any(c["held"] for c in chunks)
    out["max_block_z_cm"] = 100 * max(blocks) if blocks else None
    return out


def run_chain_task(checkpoint: str, seed: int, index: int, position: int, task: str, budget_extra: int) -> dict:
    """One stored chain rerun up to its `task` (at 1-based `position`), traced."""
    from trivla_drake.eval.episode import derive_seed, run_chain, shared_env
    from trivla_drake.eval.evaluate import _policy
    from trivla_drake.eval.home_first import HomeFirst
    from trivla_drake.tasks.suite import TASKS

    budget = TASKS[task].max_steps
    TASKS[task].max_steps = budget + budget_extra
    try:
        policy = _policy(checkpoint)
        env = shared_env(224 if policy.uses_images else None)  # the env run_chain steps
        recorder = ChunkRecorder(policy, env)
        result = run_chain(derive_seed(seed, "chain", index), HomeFirst(recorder), length=position)
    finally:
        TASKS[task].max_steps = budget
    row = {"task": task, "seed": seed, "chain": index, "position": position,
           "before": [[s.task, s.success, s.steps] for s in result.subtasks[:position - 1]],
           "reached": len(result.subtasks) == position and result.subtasks[-1].task == task}
    if not row["reached"]:  # an earlier task failed this time (another CPU rounds differently)
        return row
    record, sub = recorder.tasks[position - 1], result.subtasks[position - 1]
    return {**row, "instruction": sub.instruction, **outcome(sub.success, sub.steps, budget, budget_extra),
            "start": record["start"], **grasp_trace(record)}


def outcome(success: bool, steps: int, budget: int, budget_extra: int) -> dict:
    """Success within the task's budget and within the extended one: the trajectory up to the budget's last
    step does not depend on the budget, so one run with the longer budget gives both."""
    return {"success": bool(success and steps <= budget), "success_extended": bool(success), "steps": steps,
            "budget": budget, "budget_extended": budget + budget_extra}


def run_single_task(checkpoint: str, seed: int, index: int, task: str, budget_extra: int) -> dict:
    """`evaluate --episodes 2 --seed seed`'s episode `index` of `task`, traced."""
    from trivla_drake.eval.episode import derive_seed, run_episode, shared_env
    from trivla_drake.eval.evaluate import _policy
    from trivla_drake.tasks.suite import TASKS

    policy = _policy(checkpoint)
    env = shared_env(224 if policy.uses_images else None)  # the env run_episode steps
    recorder = ChunkRecorder(policy, env)
    budget = TASKS[task].max_steps
    result = run_episode(task, derive_seed(seed, task, index), recorder, max_steps=budget + budget_extra)
    record = recorder.tasks[-1]
    return {"task": task, "seed": seed, "episode": index, "position": 0, "before": [], "reached": True,
            "instruction": result.instruction, **outcome(result.success, result.steps, budget, budget_extra),
            "start": record["start"], **grasp_trace(record)}


def stored_chain_tasks(task: str = "lift_block", files=CHAIN_FILES) -> list[tuple[int, int, int, bool]]:
    """(base seed, chain index, position (1-based), stored success) of every try of `task` in the stored chains."""
    from trivla_drake.eval.episode import derive_seed

    jobs = []
    for path in files:
        report = json.loads(Path(path).read_text())
        seed = int(report["seed"])
        # The failures list the chains that stopped early; the others completed all their tasks.
        completed = {f["seed"]: f["completed"] for f in report["chains"]["failures"]}
        for index, tasks in enumerate(report["chains"]["tasks"]):
            done = completed.get(derive_seed(seed, "chain", index), len(tasks))
            for position, name in enumerate(tasks, start=1):
                if name == task:
                    jobs.append((seed, index, position, position <= done))
    return jobs


def _seed_range(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("out")
    parser.add_argument("--task", default="lift_block", choices=TRACED_TASKS, help="the task to trace")
    parser.add_argument("--budget-extra", type=int, default=108, help="more steps for the task, beyond its budget")
    parser.add_argument("--single-seeds", default=None, help="A-B: also trace the task's single episodes of these seeds")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    if args.budget_extra < 0:
        parser.error(f"--budget-extra must be >= 0 (steps), got {args.budget_extra}")
    from trivla_drake.eval.evaluate import _worker_init

    chain_jobs = stored_chain_tasks(args.task)
    single_jobs = [(s, i) for s in _seed_range(args.single_seeds) for i in range(2)] if args.single_seeds else []
    with ProcessPoolExecutor(args.workers, initializer=_worker_init) as pool:
        chains = list(pool.map(run_chain_task, *zip(*[(args.checkpoint, s, i, p, args.task, args.budget_extra)
                                                      for s, i, p, _ in chain_jobs])))
        singles = list(pool.map(run_single_task, *zip(*[(args.checkpoint, s, i, args.task, args.budget_extra)
                                                        for s, i in single_jobs]))) if single_jobs else []
    for row, (_, _, _, stored) in zip(chains, chain_jobs):
        row["stored_success"] = stored
    out = {"checkpoint": args.checkpoint, "task": args.task, "budget_extra": args.budget_extra,
           "chain_tasks": chains, "single_tasks": singles}
    Path(args.out).write_text(json.dumps(out, indent=1))
    reached = [r for r in chains if r["reached"]]
    print(f"{args.task} in chains, reached: {len(reached)} of {len(chains)}; succeeded {sum(r['success'] for r in reached)} "
          f"({sum(r['success_extended'] for r in reached)} with {args.budget_extra} more steps); "
          f"the stored run: {sum(s for *_, s in chain_jobs)} of {len(chain_jobs)}")
    if singles:
        print(f"single episodes: {sum(r['success'] for r in singles)} of {len(singles)} "
              f"({sum(r['success_extended'] for r in singles)} with {args.budget_extra} more steps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
