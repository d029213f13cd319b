"""Along the shipped model's stack episodes (seeds 1000-1002, 2 episodes each), at every chunk with no block
held: is GROUNDING's sub-goal nearer the block to pick up (named first) or the destination? Usage, from the
repository root: python results/stack_carry/approach_subgoals.py trivla|CHECKPOINT OUT.json"""
import json, sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
import numpy as np

def episode(job):
    grounding, seed, index = job
    import torch
    torch.set_num_threads(1)
    from trivla_drake.eval.episode import derive_seed, run_episode, shared_env
    from trivla_drake.eval.policies import load_policy
    env = shared_env(224)
    model = load_policy(grounding).model
    driver = load_policy("trivla")
    log = []
    class Logged:
        def __getattr__(self, n): return getattr(driver, n)
        def reset(self, *a, **k): return driver.reset(*a, **k)
        def act(self, obs):
            scene = env.scene()
            if not any(scene.is_held(c) for c in scene.blocks):
                g = model.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
                log.append((g, {c: scene.block_position(c).copy() for c in scene.blocks}))
            return driver.act(obs)
    result = run_episode("stack_block", derive_seed(seed, "stack_block", index), Logged(), image_size=224)
    top, base = result.params
    nearer_top = sum(1 for g, p in log if np.linalg.norm(g[:2] - p[top][:2]) < np.linalg.norm(g[:2] - p[base][:2]))
    return {"seed": seed, "index": index, "chunks": len(log), "nearer_top": nearer_top}

if __name__ == "__main__":
    jobs = [(sys.argv[1], s, i) for s in (1000, 1001, 1002) for i in (0, 1)]
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        rows = list(pool.map(episode, jobs))
    json.dump(rows, open(sys.argv[2], "w"), indent=1)
    print(sys.argv[1], sum(r["nearer_top"] for r in rows), "/", sum(r["chunks"] for r in rows), rows)
