"""Diagnostic (results/stacked_subgoal/, run from the repository root): does the shipped System 1 pick a block off
another block when its sub-goal says where that block is? Lift, place in bowl and stack with the block to pick on top
of another (`evaluate --stacked-picks --episodes 2`), the sub-goal position System 1's offset path reads being:

- `grounding`: the grounding's own (the shipped model, nothing replaced; its sub-goal is still recorded);
- `z`: the grounding's x-y with the oracle's height (where the task's plan, made from the current scene, first closes);
- `xyz`: the oracle's position, all three axes.

While a block is held the grounding's own is used in every mode (as in ../subgoal_diagnostics/true_subgoal.py).
Each chunk planned with no block held records the grounding's position and the oracle's, so OUT/MODE_seedS.json
also says how far off, in height and in x-y, the grounding puts the sub-goal of a stacked block.

    python results/stacked_subgoal/stacked_subgoal.py MODE SEEDS OUT_DIR [CHECKPOINT]
"""
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import torch

from trivla_drake.eval import evaluate as ev
from trivla_drake.nn.panda_tcp import denormalize_position, normalize_position
from trivla_drake.tasks.suite import STACKED_PICK_TASKS


def _true_subgoal_module():
    path = Path(__file__).resolve().parents[1] / "subgoal_diagnostics" / "true_subgoal.py"
    spec = importlib.util.spec_from_file_location("true_subgoal", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


TrueSubgoal = _true_subgoal_module().TrueSubgoal

AXES = {"grounding": (), "z": (2,), "xyz": (0, 1, 2)}


class StackedSubgoal(TrueSubgoal):
    """TrueSubgoal with only the axes in `self.axes` replaced, recording the grounding's own position beside the
    oracle's for every chunk planned with no block held (`self.records`, tagged with the episode's number)."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.axes: tuple[int, ...] = ()
        self.records: list[dict] = []
        self.episode = -1
        pol = self.model.policy
        own = type(pol)._ground.__get__(pol)
        me = self

        def ground(vl, vl_mask, tcp, *rest):
            goal, sub = own(vl, vl_mask, tcp, *rest)
            if me.true is not None:
                predicted = denormalize_position(sub[0, :3].detach().float()).numpy()
                me.records.append({"episode": me.episode, "predicted": predicted.tolist(),
                                   "true": np.asarray(me.true).tolist()})
                if me.axes:
                    sub = sub.clone()
                    true = normalize_position(torch.as_tensor(me.true, dtype=sub.dtype))
                    for axis in me.axes:
                        sub[:, axis] = true[axis]
            return goal, sub

        pol._ground = ground

    def reset(self, instruction: str, seed: int) -> None:
        self.episode += 1
        super().reset(instruction, seed)


def summarise(records: list[dict]) -> dict:
    """The grounding's sub-goal error (predicted - oracle) [cm]: the height's median and 10th / 90th percentiles and
    the x-y distance's median, over every chunk planned with no block held and over each episode's first such chunk."""
    def stats(rows):
        if not rows:
            return {}
        d = np.array([np.subtract(r["predicted"], r["true"]) for r in rows]) * 100.0
        return {"chunks": len(rows), "dz_median_cm": float(np.median(d[:, 2])),
                "dz_p10_p90_cm": [float(np.percentile(d[:, 2], 10)), float(np.percentile(d[:, 2], 90))],
                "xy_median_cm": float(np.median(np.linalg.norm(d[:, :2], axis=1)))}
    firsts, seen = [], set()
    for r in records:
        if r["episode"] not in seen:
            seen.add(r["episode"])
            firsts.append(r)
    return {"every_chunk": stats(records), "first_chunk": stats(firsts)}


def main() -> None:
    mode, seeds, out = sys.argv[1], [int(s) for s in sys.argv[2].split(",")], Path(sys.argv[3])
    checkpoint = sys.argv[4] if len(sys.argv) > 4 else "models/trivla_cpu"
    if mode not in AXES:
        raise SystemExit(f"MODE must be one of {', '.join(AXES)}, not {mode!r}")
    torch.set_num_threads(1)
    policy = StackedSubgoal.from_checkpoint(checkpoint)
    policy.axes = AXES[mode]
    policy.name = f"trivla+stacked_subgoal_{mode}"
    ev._POLICY_CACHE[ev.EvalConfig(policy="trivla").policy_key()] = policy
    out.mkdir(parents=True, exist_ok=True)
    for s in seeds:
        policy.records, policy.episode = [], -1
        r = ev.evaluate(ev.EvalConfig(policy="trivla", tasks=list(STACKED_PICK_TASKS), episodes=2, seed=s, workers=1,
                                      stacked_picks=True), progress=False)
        r["subgoal_records"] = policy.records
        r["subgoal_error"] = summarise(policy.records)
        (out / f"{mode}_seed{s}.json").write_text(json.dumps(r, indent=1, default=str))
        print(s, mode, {t: v["successes"] for t, v in r["tasks"].items()}, r["subgoal_error"]["first_chunk"],
              flush=True)


if __name__ == "__main__":
    main()
