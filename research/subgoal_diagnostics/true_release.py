"""Diagnostic (session 46, run from the repository root): do place in bowl and stack fail for the sub-goal System 1
reads while it carries the block? The model's sub-goal position replaced, in System 1's sub-goal offset path only, by
the release position of the oracle's plan (drawn in the episode's first scene) while the task's block is held; before
the grasp the grounding's own sub-goal is kept. Same episodes as `evaluate --episodes 2 --seed S`.

python results/subgoal_diagnostics/true_release.py SEEDS OUT_DIR [CHECKPOINT]

writes OUT_DIR/release_seedS.json for each of the comma-separated SEEDS (CHECKPOINT: models/trivla_cpu)."""
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from true_subgoal import TrueSubgoal  # noqa: E402  (a script beside this one, not a package)

from trivla_drake.action import GRIPPER_OPEN  # noqa: E402
from trivla_drake.eval import evaluate as ev  # noqa: E402
from trivla_drake.tasks.suite import get_task  # noqa: E402

TASKS = ["place_in_bowl", "stack_block"]


class TrueRelease(TrueSubgoal):
    """TrueSubgoal's override with the oracle's release position while the task's block is in the hand."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.release = None  # this episode's release position [m], from the plan at its first chunk

    def reset(self, instruction, seed):
        self.release = None
        return super().reset(instruction, seed)

    def true_position(self, scene, inst):
        if self.release is None:
            opens = [wp for wp in get_task(inst.task).plan(inst.params, scene) if wp.gripper == GRIPPER_OPEN]
            self.release = np.asarray(opens[-1].pose[:3, 3], dtype=np.float64)
        return self.release if scene.is_held(inst.params[0]) else None


def main() -> None:
    seeds, out = [int(s) for s in sys.argv[1].split(",")], Path(sys.argv[2])
    torch.set_num_threads(1)
    policy = TrueRelease.from_checkpoint(sys.argv[3] if len(sys.argv) > 3 else "models/trivla_cpu")
    policy.name = "trivla+true_release"
    ev._POLICY_CACHE[ev.EvalConfig(policy="trivla").policy_key()] = policy
    out.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        report = ev.evaluate(ev.EvalConfig(policy="trivla", tasks=TASKS, episodes=2, seed=seed, workers=1), progress=False)
        (out / f"release_seed{seed}.json").write_text(json.dumps(report, indent=1, default=str))
        print(seed, {t: v["successes"] for t, v in report["tasks"].items()}, f"chunks overridden: {policy.overrides}",
              flush=True)


if __name__ == "__main__":
    main()
