"""Where `--home-first` hands over to the policy: the measured arm's distance from home and its joint speed.

    python results/prelude_reset/handover_check.py > results/prelude_reset/handover.md

For two episodes each of six tasks after a one-task prelude (the first try of `evaluate --prelude 1`'s episodes
from seed 1000, the oracle's prelude; an episode whose prelude fails is left out, where evaluate would redraw it),
the homing of the first version (`run_homing(settle=False)`: it hands over once the commanded pose is home) and of
today's (`settle=True`: it also waits for the measured arm) is stepped in the simulator, and the state it hands over
in is measured: the tool-centre point's distance from the home pose, the norm of the arm's joint speeds, and the
steps the homing took (the most it may take: 108); a summary row per version, then every episode.
"""

from __future__ import annotations

import sys

import numpy as np

TASKS = ("lift_block", "push_block_left", "rotate_block_left", "open_drawer", "stack_block", "turn_on_light")


def handover_states(settle: bool, tasks=TASKS, episodes: int = 2, seed: int = 1000) -> list[dict]:
    """Per episode: the task, the prelude, the distance from home [cm], the joint speed norm [rad/s], the steps."""
    from trivla_drake.eval.episode import _run_prelude, derive_seed, shared_env
    from trivla_drake.eval.evaluate import _policy
    from trivla_drake.eval.home_first import home_tcp_pose, run_homing
    from trivla_drake.tasks.chains import prelude_task
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    env, oracle, home = shared_env(224), _policy("oracle"), home_tcp_pose()
    rows = []
    for task_name in tasks:
        for index in range(episodes):
            episode_seed = derive_seed(seed, task_name, index)
            rng = np.random.default_rng(episode_seed)
            spec, _ = sample_task_instance(get_task(task_name), rng, env.layout())
            obs = env.reset(spec)
            obs, _, done, why = _run_prelude(env, obs, oracle, task_name, 1,
                                             np.random.default_rng(derive_seed(episode_seed, "prelude")), False,
                                             prelude_task)
            if why:
                continue
            obs, steps = run_homing(env, obs, settle=settle, images=False)
            rows.append({"task": task_name, "prelude": done[0],
                         "to_home_cm": 100 * float(np.linalg.norm(obs["tcp_pose"][:3, 3] - home[:3, 3])),
                         "joint_speed": float(np.linalg.norm(obs["state"][9:16])), "steps": steps})
    return rows


def summary_line(label: str, rows: list[dict]) -> str:
    """One Markdown row: median and range of each measure over `rows`."""
    def spread(key, fmt):
        values = np.array([r[key] for r in rows], dtype=float)
        return f"{fmt.format(np.median(values))} ({fmt.format(values.min())}–{fmt.format(values.max())})"

    return (f"| {label} | {len(rows)} | {spread('to_home_cm', '{:.1f}')} | {spread('joint_speed', '{:.2f}')} | "
            f"{spread('steps', '{:.0f}')} |")


def main() -> int:
    lines = ["| homing | episodes | tool-centre point to home [cm], median (range) | joint speed norm [rad/s] | "
             "homing steps |", "| --- | --- | --- | --- | --- |"]
    versions = (("first version (`settle=False`)", False), ("today's `--home-first` (`settle=True`)", True))
    rows = {label: handover_states(settle) for label, settle in versions}
    lines += [summary_line(label, got) for label, got in rows.items()]
    lines += ["", "| homing | task | prelude | to home [cm] | joint speed [rad/s] | steps |",
              "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {label} | {r['task']} | {r['prelude']} | {r['to_home_cm']:.1f} | {r['joint_speed']:.2f} "
              f"| {r['steps']} |" for label, got in rows.items() for r in got]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
