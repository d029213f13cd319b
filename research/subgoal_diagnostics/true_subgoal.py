"""Diagnostic (results/subgoal_diagnostics/, run from the repository root): the shipped model with its grounding's sub-goal position replaced,
in System 1's sub-goal offset path only, by the oracle's true grasp position (while no block is held)."""
import json, sys
from pathlib import Path
import numpy as np, torch
from trivla_drake.eval import evaluate as ev
from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy
from trivla_drake.nn.panda_tcp import normalize_position
from trivla_drake.tasks.suite import get_task
from trivla_drake.action import GRIPPER_CLOSE

class TrueSubgoal(TriVLAHarnessPolicy):
    privileged = True
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.true = None
        pol = self.model.policy
        original = pol._ground
        me = self
        def ground(vl, vl_mask, tcp, *rest):  # rest: the gripper's closure, for a grounding that reads it
            goal, sub = original(vl, vl_mask, tcp, *rest)
            if me.true is not None:
                sub = sub.clone()
                sub[:, :3] = normalize_position(torch.as_tensor(me.true, dtype=sub.dtype))[None]
            return goal, sub
        pol._ground = ground
        self.overrides = 0
    def true_position(self, scene, inst):
        """The position [m] System 1 reads as its sub-goal for this chunk, or None for the grounding's own:
        here the plan's first close while no block is held."""
        if scene.held_block() is not None:
            return None
        closes = [wp for wp in get_task(inst.task).plan(inst.params, scene) if wp.gripper == GRIPPER_CLOSE]
        return np.asarray(closes[0].pose[:3, 3], dtype=np.float64) if closes else None

    def act(self, observation):
        priv = observation["privileged"]
        self.true = self.true_position(priv["scene"], priv["task"])
        self.overrides += self.true is not None
        return super().act(observation)

GRASP_TASKS = ["lift_block", "place_in_bowl", "stack_block", "rotate_block_left"]


def evaluate_seeds(policy, kind: str, seeds: list[int], out: str) -> None:
    """`evaluate --episodes 2` of the grasp tasks on each seed, in this process, as `policy`; writes
    OUT/KIND_seedS.json per seed."""
    torch.set_num_threads(1)
    ev._POLICY_CACHE[ev.EvalConfig(policy="trivla").policy_key()] = policy
    Path(out).mkdir(parents=True, exist_ok=True)
    for s in seeds:
        r = ev.evaluate(ev.EvalConfig(policy="trivla", tasks=GRASP_TASKS, episodes=2, seed=s, workers=1), progress=False)
        (Path(out) / f"{kind}_seed{s}.json").write_text(json.dumps(r, indent=1, default=str))
        print(s, r["average_success"], {t: v["successes"] for t, v in r["tasks"].items()}, flush=True)


if __name__ == "__main__":  # SEEDS OUT_DIR [CHECKPOINT (default models/trivla_cpu)]
    policy = TrueSubgoal.from_checkpoint(sys.argv[3] if len(sys.argv) > 3 else "models/trivla_cpu")
    policy.name = "trivla+true_subgoal"
    evaluate_seeds(policy, "true", [int(s) for s in sys.argv[1].split(",")], sys.argv[2])
