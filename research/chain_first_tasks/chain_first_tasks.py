"""The first task of `evaluate --chains N --seed S`'s chains, alone (a chain of length 1: the same scene,
task, instruction and policy seed as that chain's first task), with the shipped policy; two processes.

    python results/chain_first_tasks/chain_first_tasks.py SEEDS N OUT.json

SEEDS: comma-separated evaluate seeds; N: chains per seed. Prints successes per task."""

import collections
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context


def first_tasks(job: tuple[int, list[int]]) -> list[dict]:
    """The first task of chains `indices` of evaluate seed `seed`."""
    seed, indices = job
    import torch

    torch.set_num_threads(1)  # as evaluate's workers
    from trivla_drake.eval.episode import derive_seed, run_chain
    from trivla_drake.eval.policies import load_policy

    policy = load_policy("trivla")
    rows = []
    for index in indices:
        chain = run_chain(derive_seed(seed, "chain", index), policy, length=1).to_dict()
        task = chain["subtasks"][0] if chain["subtasks"] else {}
        rows.append({"seed": seed, "index": index, "task": task.get("task"), "instruction": task.get("instruction"),
                     "success": bool(task.get("success")), "steps": task.get("steps")})
    return rows


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    seeds, chains = [int(s) for s in sys.argv[1].split(",")], int(sys.argv[2])
    jobs = [(seed, list(range(start, chains, 2))) for seed in seeds for start in (0, 1)]
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        rows = [row for part in pool.map(first_tasks, jobs) for row in part]
    with open(sys.argv[3], "w") as out:
        json.dump(rows, out, indent=1)
    per_task = collections.defaultdict(lambda: [0, 0])
    for row in rows:
        per_task[row["task"]][0] += row["success"]
        per_task[row["task"]][1] += 1
    print(sum(row["success"] for row in rows), "/", len(rows),
          {task: f"{done}/{count}" for task, (done, count) in sorted(per_task.items())})
