"""Where a policy carries the block in `stack_block` episodes: towards the named destination block or
towards the third block?

For each episode (the `evaluate` episodes of `--seed S --episodes 2`: same scenes, instructions and policy
seeds), once per chunk: whether the named (top) block is held, and the xy distance from it to the named
destination (base) and to the other block; and
whether the instruction grounding's sub-goal for that observation lies nearer the destination or the other
block (a grounding model only). Usage, from the repository root:

    python results/stack_destinations/stack_destinations.py CHECKPOINT|trivla OUT.json [SEEDS] [--grounding CHECKPOINT]

With `--grounding`, the sub-goal is asked of that checkpoint's grounding instead, along the trajectories of the
first policy (which is then only the driver): another grounding judged on the same observations.
SEEDS defaults to 1000,1001,1002,1003,1004,1005; two worker processes, torch at one thread each."""

import json
import sys
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import numpy as np

TASK = "stack_block"
IMAGE_SIZE = 224  # as `evaluate` renders for an image policy


class _Logged:
    """The policy, and at each chunk it plans: which blocks are held and where they are."""

    def __init__(self, inner, env, asked=None, ask_while_held=True):
        self.inner, self.env, self.log, self.ask_while_held = inner, env, [], ask_while_held
        model = getattr(asked or inner, "model", None)  # the oracle and models without a grounding: nothing to ask
        self.grounded = model is not None and getattr(model.policy, "grounding", None) is not None
        self.asked = model

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def reset(self, *args, **kwargs):
        self.log = []
        return self.inner.reset(*args, **kwargs)

    def act(self, obs):
        scene = self.env.scene()
        holding = {c: scene.is_held(c) for c in scene.blocks}
        subgoal = None
        if self.grounded and any(holding.values()) == self.ask_while_held:  # the next event: a 2nd System 2 pass
            subgoal = self.asked.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"],
                                                 obs["state"])
        chunk = self.inner.act(obs)
        self.log.append((holding, {c: scene.block_position(c).copy() for c in scene.blocks}, subgoal))
        return chunk


def episode(job: tuple) -> dict:
    policy_spec, seed, index, grounding_spec = job
    import torch

    torch.set_num_threads(1)
    from trivla_drake.eval.episode import derive_seed, run_episode, shared_env
    from trivla_drake.eval.policies import load_policy

    env = shared_env(IMAGE_SIZE)
    policy = _Logged(load_policy(policy_spec), env, load_policy(grounding_spec) if grounding_spec else None)
    result = run_episode(TASK, derive_seed(seed, TASK, index), policy, image_size=IMAGE_SIZE)
    final = env.scene()  # as the episode left it: where the named block ended
    top, base = result.params
    row = {"seed": seed, "index": index, "instruction": result.instruction, "success": result.success,
           "held_chunks": 0}
    held = [(positions, subgoal) for holding, positions, subgoal in policy.log if holding[top]]
    if held:
        other = next(c for c in held[0][0] if c not in (top, base))
        to = {c: [float(np.linalg.norm(p[top][:2] - p[c][:2])) for p, _ in held] for c in (base, other)}
        # Chunks whose sub-goal lies nearer the destination than the other block (None without a grounding).
        subgoal_nearer = sum(1 for p, g in held if np.linalg.norm(g[:2] - p[base][:2])
                             < np.linalg.norm(g[:2] - p[other][:2])) if policy.grounded else None
        # How far (xy) the sub-goal lies from the destination block, over the chunks with the block held.
        subgoal_off = [float(np.linalg.norm(g[:2] - p[base][:2])) for p, g in held] if policy.grounded else None
        row.update(held_chunks=len(held), min_to_destination=min(to[base]), min_to_other=min(to[other]),
                   last_to_destination=to[base][-1], last_to_other=to[other][-1],
                   subgoal_nearer_destination=subgoal_nearer,
                   subgoal_to_destination_median=float(np.median(subgoal_off)) if subgoal_off else None,
                   subgoal_to_destination_last=subgoal_off[-1] if subgoal_off else None)
    # Where the named block ended (xy from the destination, and its height): on top, beside, or in the hand.
    row.update(final_to_destination=float(np.linalg.norm(final.block_position(top)[:2] - final.block_position(base)[:2])),
               final_height=float(final.block_position(top)[2]), final_held=bool(final.is_held(top)))
    return row


if __name__ == "__main__":
    args = sys.argv[1:]
    grounding = None
    if "--grounding" in args:
        at = args.index("--grounding")
        grounding = args[at + 1] if at + 1 < len(args) else sys.exit(__doc__)
        del args[at : at + 2]
    if len(args) not in (2, 3):
        sys.exit(__doc__)
    seeds = [int(s) for s in (args[2] if len(args) == 3 else "1000,1001,1002,1003,1004,1005").split(",")]
    jobs = [(args[0], seed, index, grounding) for seed in seeds for index in (0, 1)]
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        rows = list(pool.map(episode, jobs))
    with open(args[1], "w") as out:
        json.dump(rows, out, indent=1)
    print("| seed | episode | success | chunks holding the block | closest to destination / other [cm] | "
          "at the last such chunk [cm] | sub-goal nearer the destination (chunks) | sub-goal to destination, "
          "median / last held chunk [cm] | block's end: from destination [cm], height [cm] | instruction |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        near = (f"{100 * r['min_to_destination']:.1f} / {100 * r['min_to_other']:.1f} | "
                f"{100 * r['last_to_destination']:.1f} / {100 * r['last_to_other']:.1f} | "
                f"{'-' if r['subgoal_nearer_destination'] is None else r['subgoal_nearer_destination']}"
                ) if r["held_chunks"] else "- | - | -"
        off = (f"{100 * r['subgoal_to_destination_median']:.1f} / {100 * r['subgoal_to_destination_last']:.1f}"
               if r.get("subgoal_to_destination_median") is not None else "-")
        end = (f"{100 * r['final_to_destination']:.1f}, {100 * r['final_height']:.1f}"
               + (" (held)" if r["final_held"] else "")) if "final_to_destination" in r else "-"
        print(f"| {r['seed']} | {r['index']} | {'yes' if r['success'] else 'no'} | {r['held_chunks']} | {near} | "
              f"{off} | {end} | {r['instruction']} |")
