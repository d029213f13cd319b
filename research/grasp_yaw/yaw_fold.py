"""Do the grasp tasks fail where the oracle's grasp yaw flips? (session 48; run from the repository root)

A block's faces repeat every quarter turn, so the oracle's grasp yaw (`tasks.motions.grasp_yaw`) jumps by 90 degrees
where the block's yaw crosses the fold at +/-45 degrees: there the demonstrations turn the hand either way, and a
policy that cannot tell which might average the two. This script rebuilds the scenes of a stored evaluation (no
simulation) and bins its episodes' successes by how far the named block is turned from the hand at the start, by the
block's own folded yaw, and by the oracle's turn.

python results/grasp_yaw/yaw_fold.py EVALUATION.json   (e.g. results/grounding_scenes/grasp_tasks_refit.json)
"""
import json
import math
import sys

import numpy as np
import torch

from trivla_drake.eval.episode import derive_seed
from trivla_drake.nn.panda_tcp import PandaTcpFeatures
from trivla_drake.tasks.motions import grasp_yaw
from trivla_drake.tasks.scene import Layout, fold_quarter_turn, hand_yaw, scene_from_spec
from trivla_drake.tasks.suite import get_task, sample_task_instance

# Bin edges [deg] of the absolute angles; the last bin ends past 45 so that the fold itself is in it.
FOLD_EDGES = (0, 15, 30, 38, 46)
TURN_EDGES = (0, 15, 30, 45, 60, 180.1)  # turns are wrapped into [-180, 180]


def episode_yaws(report: dict, layout: Layout | None = None) -> list[dict]:
    """One row per episode of `report` (an `evaluate --json` report of tasks whose first argument is a block):
    its success and, in degrees, the named block's yaw folded into [-45, 45), the hand's start yaw, the block
    against the hand (folded), and the oracle's turn from the start yaw to its grasp yaw."""
    layout = layout or Layout.default()
    tcp = PandaTcpFeatures()
    rows = []
    for name, task in report["tasks"].items():
        failed = {f["seed"] for f in task["failures"]}
        for index in range(task["episodes"]):
            seed = derive_seed(report["seed"], name, index)  # as `evaluate` draws episode `index` of `name`
            spec, instance = sample_task_instance(get_task(name), np.random.default_rng(seed), layout)
            scene = scene_from_spec(spec, layout)
            color = instance.params[0]
            with torch.no_grad():
                start = hand_yaw(tcp.pose(torch.tensor(np.asarray(spec.arm_q)[None], dtype=torch.float64))[0].numpy())
            block = fold_quarter_turn(scene.block_yaw(color))
            rows.append({"task": name, "seed": seed, "success": seed not in failed,
                         "block_deg": math.degrees(block), "hand_deg": math.degrees(start),
                         "off_deg": math.degrees(fold_quarter_turn(block - start)),
                         "turn_deg": math.degrees(math.remainder(grasp_yaw(scene, color) - start, 2 * math.pi))})
    return rows


def binned(rows: list[dict], key: str, edges, task: str | None = None) -> list[tuple[float, float, int, int]]:
    """(low, high, episodes, successes) for each bin of |row[key]| between consecutive `edges`."""
    chosen = [r for r in rows if task is None or r["task"] == task]
    out = []
    for low, high in zip(edges, edges[1:]):
        inside = [r for r in chosen if low <= abs(r[key]) < high]
        out.append((low, high, len(inside), sum(r["success"] for r in inside)))
    return out


def markdown(rows: list[dict]) -> str:
    tasks = sorted({r["task"] for r in rows})
    lines = ["| the named block against the hand at the start, folded [deg] | " + " | ".join(tasks) + " | all |",
             "| --- |" + " --- |" * (len(tasks) + 1)]
    columns = [binned(rows, "off_deg", FOLD_EDGES, t) for t in tasks] + [binned(rows, "off_deg", FOLD_EDGES)]
    for i, (low, high) in enumerate(zip(FOLD_EDGES, FOLD_EDGES[1:])):
        lines.append(f"| {low}-{high} | " + " | ".join(f"{c[i][3]} / {c[i][2]}" for c in columns) + " |")
    for key, edges, title in (("block_deg", FOLD_EDGES, "the block's own yaw, folded"),
                              ("turn_deg", TURN_EDGES, "the oracle's turn to its grasp yaw")):
        lines += ["", f"| {title} [deg] | successes / episodes |", "| --- | --- |"]
        lines += [f"| {low}-{high:g} | {s} / {n} |" for low, high, n, s in binned(rows, key, edges)]
    return "\n".join(lines)


def main() -> None:
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    print(markdown(episode_yaws(json.load(open(sys.argv[1])))))


if __name__ == "__main__":
    main()
