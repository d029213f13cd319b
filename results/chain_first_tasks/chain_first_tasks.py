"""The first task of `evaluate --chains N --seed S`'s chains, alone (a chain of length 1: the same scene,
task, instruction and policy seed as that chain's first task), with the shipped policy; two processes.

    python results/chain_first_tasks/chain_first_tasks.py SEEDS N OUT.json

SEEDS: comma-separated evaluate seeds; N: chains per seed. Prints successes per task.
"""
import sys, json
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

def work(args):
    seed, indices = args
    import torch; torch.set_num_threads(1)
    from trivla_drake.eval.episode import run_chain, derive_seed
    from trivla_drake.eval.policies import load_policy
    p = load_policy("trivla", None)
    out = []
    for j in indices:
        r = run_chain(derive_seed(seed, "chain", j), p, length=1).to_dict()
        s = r["subtasks"][0] if r["subtasks"] else {}
        out.append({"seed": seed, "index": j, "task": s.get("task"), "instruction": s.get("instruction"),
                    "success": bool(s.get("success")), "steps": s.get("steps")})
    return out

if __name__ == "__main__":
    seeds = [int(s) for s in sys.argv[1].split(",")]; n = int(sys.argv[2])
    jobs = [(s, list(range(k, n, 2))) for s in seeds for k in (0, 1)]
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        res = [r for part in pool.map(work, jobs) for r in part]
    json.dump(res, open(sys.argv[3], "w"), indent=1)
    import collections
    c = collections.defaultdict(lambda: [0, 0])
    for r in res: c[r["task"]][0] += r["success"]; c[r["task"]][1] += 1
    print(sum(r["success"] for r in res), "/", len(res), {t: f"{a}/{b}" for t, (a, b) in sorted(c.items())})
