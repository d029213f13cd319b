"""Do the tasks after a chain prelude fail on the scene the prelude left, or on the state it left the robot in?

Runs `evaluate --prelude 1`'s episodes (the same seeds, preludes, tasks, instructions and policy seeds: paired
with a stored `evaluate --prelude 1 --json` file), but once the oracle's prelude is done the simulation is
started again (`TabletopEnv.reset`, time 0, a fresh diff-IK solver) from a SceneSpec of what the prelude
left: every block where it lies (upright, at its yaw about z), the drawer's opening and the lamp as they are,
and the arm back in the episode's start posture with the hand open (`--arm start`). The policy then gets the
task as it would from the start posture, with no scripted motion and no step of the task's budget spent.
`--arm prelude` restarts it the same way with the arm where the prelude left it (the hand opened);
`--arm home` does not restart: the first version of `evaluate --home-first`'s homing (`run_homing(settle=False)`)
brings the hand home, its steps outside the task's budget.

    python results/prelude_reset/reset_after_prelude.py CHECKPOINT SEED OUT.json [--arm start|prelude|home]

OUT.json has `evaluate --json`'s per-task form (tasks -> successes, episodes, failures), plus every episode:
its seed, prelude, instruction, success, the commanded pose's offset from the measured one when the prelude
ended, whether the gripper was closed then, and (`--arm home`) the homing's steps.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def scene_spec_after(scene, arm_q):
    """A SceneSpec of `scene` (a SceneState): the blocks upright where they lie, the drawer and lamp as they
    are, the arm at `arm_q` (the hand opens: SceneSpecs start it open)."""
    from trivla_drake.tasks.scene import BlockPlacement, SceneSpec

    blocks = {c: BlockPlacement(tuple(float(v) for v in scene.block_position(c)), float(scene.block_yaw(c)))
              for c in scene.blocks}
    return SceneSpec(blocks=blocks, drawer_opening=float(scene.drawer_opening), lamp_on=bool(scene.lamp_on),
                     arm_q=tuple(float(q) for q in arm_q))


def restart_after_prelude(env, obs: dict, start_arm_q, arm: str) -> tuple[dict, int | None]:
    """What follows the prelude: "start" and "prelude" restart the env at time 0 from the scene the prelude left,
    the arm at `start_arm_q` (the episode's start posture) or where the prelude left it; "home" does not restart,
    the first version's homing brings the hand home. Returns (observation, homing steps or None)."""
    if arm == "home":
        from trivla_drake.eval.home_first import run_homing

        return run_homing(env, obs, settle=False)
    if arm not in ("start", "prelude"):
        raise ValueError(f"arm must be start, prelude or home, got {arm!r}")
    scene = env.scene()
    return env.reset(scene_spec_after(scene, start_arm_q if arm == "start" else scene.arm_q)), None


def run_reset_episode(checkpoint: str, task_name: str, seed: int, index: int, arm: str = "start") -> dict:
    """`evaluate --prelude 1`'s episode `index` of `task_name` from base seed `seed`, after its prelude restarted
    with the arm in the episode's start posture (`arm` "start") or where the prelude left it ("prelude"), or homed
    by the first version of --home-first without a restart, its steps not counted ("home"). An exception (a
    simulation failure) fails the episode with its reason, as in `run_episode`."""
    try:
        return _reset_episode(checkpoint, task_name, seed, index, arm)
    except Exception as error:  # noqa: BLE001 - one episode's failure, the run goes on
        return {"task": task_name, "seed": None, "prelude": [], "success": False,
                "reason": f"{type(error).__name__}: {error}"}


def _reset_episode(checkpoint: str, task_name: str, seed: int, index: int, arm: str) -> dict:
    from trivla_drake.eval.episode import _Recorder, _run_prelude, _run_subtask, derive_seed, shared_env
    from trivla_drake.eval.evaluate import PRELUDE_REDRAWS, _policy
    from trivla_drake.tasks.chains import prelude_task
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    policy, oracle = _policy(checkpoint), _policy("oracle")
    task = get_task(task_name)
    env = shared_env(224)
    base = derive_seed(seed, task_name, index)
    for redraw in range(PRELUDE_REDRAWS + 1):
        episode_seed = base if redraw == 0 else derive_seed(seed, task_name, index, "prelude", redraw)
        rng = np.random.default_rng(episode_seed)
        spec, _ = sample_task_instance(task, rng, env.layout())
        policy_seed = int(rng.integers(2**31))
        obs = env.reset(spec)
        obs, instance, done, why = _run_prelude(env, obs, oracle, task_name, 1,
                                                np.random.default_rng(derive_seed(episode_seed, "prelude")), False,
                                                prelude_task)
        if not why:
            break
    row = {"task": task_name, "seed": episode_seed, "prelude": done, "success": False}
    if why:
        return {**row, "reason": why}
    row["instruction"] = instance.instruction
    target_offset = obs["ee_target"][:3, 3] - obs["tcp_pose"][:3, 3]
    row["target_offset_cm"] = [round(100 * float(v), 2) for v in target_offset]
    row["gripper_closed_after_prelude"] = bool(obs["gripper_command"] <= 0)
    obs, homing_steps = restart_after_prelude(env, obs, spec.arm_q, arm)
    if homing_steps is not None:  # the first version's homing, its steps outside the task's budget
        row["homing_steps"] = homing_steps
    if tuple(instance.params) not in [tuple(p) for p in task.candidates(env.scene())]:
        return {**row, "reason": "the reset scene no longer lets the task start", "startable": False}
    result, _ = _run_subtask(env, obs, policy, instance, policy_seed, task.max_steps,
                             _Recorder(False, None, env.action_space.control_rate_hz))
    return {**row, "success": bool(result.success), "reason": result.reason, "startable": True}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("seed", type=int)
    parser.add_argument("out")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--arm", choices=("start", "prelude", "home"), default="start",
                        help="the arm after the reset: the episode's start posture, or where the prelude left it; "
                             "home: no reset, the first version of --home-first's homing, its steps not counted")
    args = parser.parse_args(argv)
    from trivla_drake.tasks.suite import TASK_NAMES

    jobs = [(args.checkpoint, name, args.seed, k, args.arm) for name in TASK_NAMES for k in range(args.episodes)]
    from trivla_drake.eval.evaluate import _worker_init

    with ProcessPoolExecutor(args.workers, initializer=_worker_init) as pool:
        rows = list(pool.map(run_reset_episode, *zip(*jobs)))
    tasks = {}
    for row in rows:
        t = tasks.setdefault(row["task"], {"episodes": 0, "successes": 0, "failures": []})
        t["episodes"] += 1
        t["successes"] += row["success"]
        if not row["success"]:
            t["failures"].append({k: row.get(k) for k in ("seed", "instruction", "reason", "prelude")})
    report = {"policy": args.checkpoint, "seed": args.seed, "episodes_per_task": args.episodes, "arm": args.arm,
              "average_success": sum(r["success"] for r in rows) / len(rows), "tasks": tasks, "episodes": rows}
    Path(args.out).write_text(json.dumps(report, indent=1))
    print(f"{sum(r['success'] for r in rows)} of {len(rows)} after a prelude (--arm {args.arm})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
