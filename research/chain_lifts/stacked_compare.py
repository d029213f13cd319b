"""Lift, stack and place with the block to pick up on top of another, against the same tasks' usual scenes.

    python results/chain_lifts/stacked_compare.py > results/chain_lifts/stacked_picks/compare.md

Rows: the oracle and the shipped model on `evaluate --stacked-picks` (stacked_picks/*_seedS.json, S = 1000-1005),
and the shipped model on the usual single-task scenes of the same seeds, as `chain_lifts.py --single-seeds` traced
them on the same machine (the `single_tasks` of lifts.json, stack.json, place.json; those ran 108 steps more than
the budget, and a success counts only within the budget, as evaluate counts it).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
TASKS = ("lift_block", "stack_block", "place_in_bowl")
SEEDS = tuple(range(1000, 1006))
TRACES = {"lift_block": "lifts.json", "stack_block": "stack.json", "place_in_bowl": "place.json"}


def stacked_counts(policy: str, folder: Path = HERE / "stacked_picks") -> dict[str, tuple[int, int]]:
    """task -> (successes, episodes) over the seeds' `evaluate --stacked-picks` files of `policy`."""
    counts = {task: [0, 0] for task in TASKS}
    for seed in SEEDS:
        report = json.loads((folder / f"{policy}_seed{seed}.json").read_text())
        for task in TASKS:
            counts[task][0] += report["tasks"][task]["successes"]
            counts[task][1] += report["tasks"][task]["episodes"]
    return {task: tuple(c) for task, c in counts.items()}


def usual_counts(folder: Path = HERE) -> dict[str, tuple[int, int]]:
    """task -> (successes, episodes) of the traced single episodes of the same seeds."""
    out = {}
    for task in TASKS:
        rows = [r for r in json.loads((folder / TRACES[task]).read_text())["single_tasks"] if r["seed"] in SEEDS]
        out[task] = (sum(r["success"] for r in rows), len(rows))
    return out


def table() -> str:
    rows = (("oracle, block on top of another (`--stacked-picks`)", stacked_counts("oracle")),
            ("shipped, block on top of another (`--stacked-picks`)", stacked_counts("shipped")),
            ("shipped, the usual scenes (no stack)", usual_counts()))
    lines = ["| seeds 1000-1005, 2 episodes per task | " + " | ".join(TASKS) + " | all |",
             "| --- | " + " | ".join("---" for _ in TASKS) + " | --- |"]
    for label, counts in rows:
        won, tried = sum(c[0] for c in counts.values()), sum(c[1] for c in counts.values())
        lines.append(f"| {label} | " + " | ".join(f"{counts[t][0]} / {counts[t][1]}" for t in TASKS)
                     + f" | {won} / {tried} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(table())
    sys.exit(0)
