"""Along the shipped model's stack episodes (seeds 1000-1002, 2 episodes each), at every chunk with no block
held: is GROUNDING's sub-goal nearer the block to pick up (named first) or the destination? Usage, from the
repository root:

    python results/stack_carry/approach_subgoals.py trivla|CHECKPOINT OUT.json"""

import json
import sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "stack_destinations"))
from stack_destinations import IMAGE_SIZE, TASK, _Logged  # noqa: E402  (the same logging wrapper)


def episode(job: tuple) -> dict:
    grounding, seed, index = job
    import torch

    torch.set_num_threads(1)
    from trivla_drake.eval.episode import derive_seed, run_episode, shared_env
    from trivla_drake.eval.policies import load_policy

    env = shared_env(IMAGE_SIZE)
    policy = _Logged(load_policy("trivla"), env, load_policy(grounding), ask_while_held=False)
    result = run_episode(TASK, derive_seed(seed, TASK, index), policy, image_size=IMAGE_SIZE)
    top, base = result.params
    asked = [(positions, subgoal) for _, positions, subgoal in policy.log if subgoal is not None]
    nearer_top = sum(1 for p, g in asked if np.linalg.norm(g[:2] - p[top][:2]) < np.linalg.norm(g[:2] - p[base][:2]))
    return {"seed": seed, "index": index, "chunks": len(asked), "nearer_top": nearer_top}


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    jobs = [(sys.argv[1], seed, index) for seed in (1000, 1001, 1002) for index in (0, 1)]
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        rows = list(pool.map(episode, jobs))
    with open(sys.argv[2], "w") as out:
        json.dump(rows, out, indent=1)
    print(sys.argv[1], sum(r["nearer_top"] for r in rows), "/", sum(r["chunks"] for r in rows))
