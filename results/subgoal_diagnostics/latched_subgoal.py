"""Diagnostic (results/subgoal_diagnostics/, run from the repository root): the shipped model with its grounding's sub-goal position latched:
the first chunk's prediction is reused by System 1's sub-goal offset path until the policy first commands
the gripper closed; after that, each chunk's own prediction (no privileged information)."""
import json, sys
from pathlib import Path
import numpy as np, torch
from trivla_drake.eval import evaluate as ev
from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy

class LatchedSubgoal(TriVLAHarnessPolicy):
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.latched, self.closed = None, False
        pol = self.model.policy
        original = pol._ground
        me = self
        def ground(vl, vl_mask, tcp):
            goal, sub = original(vl, vl_mask, tcp)
            if not me.closed:
                if me.latched is None:
                    me.latched = sub[:, :3].clone()
                else:
                    sub = sub.clone()
                    sub[:, :3] = me.latched
            return goal, sub
        pol._ground = ground
    def reset(self, instruction, seed):
        super().reset(instruction, seed)
        self.latched, self.closed = None, False
    def act(self, observation):
        chunk = super().act(observation)
        if (chunk[:, 6] < 0).any():
            self.closed = True
        return chunk

seeds = [int(s) for s in sys.argv[1].split(",")]
out = sys.argv[2]
torch.set_num_threads(1)
policy = LatchedSubgoal.from_checkpoint("models/trivla_cpu")
ev._POLICY_CACHE[("trivla", None, None, None)] = policy
for s in seeds:
    r = ev.evaluate(ev.EvalConfig(policy="trivla", tasks=["lift_block", "place_in_bowl", "stack_block", "rotate_block_left"],
                                  episodes=2, seed=s, workers=1), progress=False)
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / f"latched_seed{s}.json").write_text(json.dumps(r, indent=1, default=str))
    print(s, r["average_success"], flush=True)
