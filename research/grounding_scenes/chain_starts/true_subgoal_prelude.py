"""Diagnostic (session 45, run from the repository root): after a one-task chain prelude, do the grasp tasks fail
for the grounding's sub-goal? The model's sub-goal position replaced, in System 1's sub-goal offset path only, by the
oracle's grasp position while no block is held (`../../subgoal_diagnostics/true_subgoal.py`'s TrueSubgoal), on the
same episodes as `evaluate --episodes 2 --prelude 1 --seed S`.

python results/grounding_scenes/chain_starts/true_subgoal_prelude.py SEEDS OUT_PREFIX [CHECKPOINT]

writes OUT_PREFIX_seedS.json for each of the comma-separated SEEDS (CHECKPOINT: models/trivla_cpu)."""
import importlib.util
import json
import sys
from pathlib import Path

import torch

from trivla_drake.eval import evaluate as ev

TASKS = ["lift_block", "place_in_bowl", "stack_block", "rotate_block_left"]


def true_subgoal_policy(checkpoint: str):
    path = Path(__file__).resolve().parents[2] / "subgoal_diagnostics" / "true_subgoal.py"
    spec = importlib.util.spec_from_file_location("true_subgoal", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    policy = module.TrueSubgoal.from_checkpoint(checkpoint)
    policy.name = "trivla+true_subgoal"
    return policy


def main() -> None:
    seeds, prefix = [int(s) for s in sys.argv[1].split(",")], sys.argv[2]
    torch.set_num_threads(1)
    ev._POLICY_CACHE[ev.EvalConfig(policy="trivla").policy_key()] = true_subgoal_policy(sys.argv[3] if len(sys.argv) > 3 else "models/trivla_cpu")
    for seed in seeds:
        config = ev.EvalConfig(policy="trivla", tasks=TASKS, episodes=2, seed=seed, workers=1, prelude=1)
        report = ev.evaluate(config, progress=False)
        Path(f"{prefix}_seed{seed}.json").write_text(json.dumps(report, indent=1, default=str))
        print(seed, {t: v["successes"] for t, v in report["tasks"].items()}, flush=True)


if __name__ == "__main__":
    main()
