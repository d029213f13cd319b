"""Diagnostic (results/subgoal_diagnostics/, run from the repository root): the shipped model with its grounding's sub-goal position latched:
the first chunk's prediction is reused by System 1's sub-goal offset path until the policy first commands
the gripper closed; after that, each chunk's own prediction (no privileged information)."""
import sys
import torch
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

if __name__ == "__main__":
    from true_subgoal import evaluate_seeds  # this folder, beside this script

    evaluate_seeds(LatchedSubgoal.from_checkpoint("models/trivla_cpu"), "latched",
                   [int(s) for s in sys.argv[1].split(",")], sys.argv[2])
