"""Diagnostic (results/subgoal_diagnostics/, run from the repository root): which part of the grounding's
sub-goal error matters. As true_subgoal.py, but only some axes of the position System 1's offset path
reads are the oracle's: `z` (the oracle's height, the grounding's x-y) or `xy` (the oracle's x-y, the
grounding's height). `python results/subgoal_diagnostics/split_subgoal.py xy 1000,1001,1002 OUT_DIR`."""
import sys
sys.path.insert(0, "results/subgoal_diagnostics")
import torch
from true_subgoal import TrueSubgoal, evaluate_seeds
from trivla_drake.nn.panda_tcp import normalize_position

if __name__ == "__main__":
    mode = sys.argv[1]
    replace = {"z": (2,), "xy": (0, 1)}[mode]
    policy = TrueSubgoal.from_checkpoint("models/trivla_cpu")
    pol = policy.model.policy
    base = type(pol)._ground.__get__(pol)
    def ground(vl, vl_mask, tcp):
        goal, sub = base(vl, vl_mask, tcp)
        if policy.true is not None:
            sub = sub.clone()
            true = normalize_position(torch.as_tensor(policy.true, dtype=sub.dtype))
            for axis in replace:
                sub[:, axis] = true[axis]
        return goal, sub
    pol._ground = ground
    policy.name = f"trivla+true_{mode}"
    evaluate_seeds(policy, f"true_{mode}", [int(s) for s in sys.argv[2].split(",")], sys.argv[3])
