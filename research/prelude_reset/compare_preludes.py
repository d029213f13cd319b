"""The tables of results/prelude_reset/README.md, from the stored evaluations (nothing is simulated).

    python results/prelude_reset/compare_preludes.py [--root RESULTS_DIR] > results/prelude_reset/compare.md

Every task after a one-task prelude (seeds 1000-1002, two episodes per task: the same 72 scenes, preludes,
instructions and policy seeds in each row), the shipped model run six ways, with the same tasks from the start
posture below them; each row's episodes won and lost against the first row's, with the exact McNemar test
(`../follow_control/compare_seeds.py`); then
the 80 chains (seeds 1003-1006) without and with `--home-first`, paired by chain.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "follow_control"))
from compare_seeds import mcnemar_p, stderr  # noqa: E402 - a sibling results script, run as a file

TASKS = ("lift_block", "place_in_bowl", "stack_block", "unstack_block", "push_block_left", "push_block_right",
         "rotate_block_left", "rotate_block_right", "open_drawer", "close_drawer", "turn_on_light", "turn_off_light")
SHORT = ("lift", "place", "stack", "unstack", "push L", "push R", "rot L", "rot R", "open", "close", "on", "off")
SEEDS = (1000, 1001, 1002)
CHAIN_SEEDS = (1003, 1004, 1005, 1006)
CHAINS_PER_SEED = 20
# (label, file prefix under the results folder); the first row is what the others are paired with.
PRELUDE_ROWS = (
    ("after the prelude, as `evaluate --prelude 1`", "grounding_scenes/refit_prelude1"),
    ("restarted at time 0, the arm in its start posture (`--arm start`)", "prelude_reset/reset_prelude1"),
    ("restarted at time 0, the arm where the prelude left it (`--arm prelude`)", "prelude_reset/armkept_prelude1"),
    ("first version of `--home-first` (its steps counted)", "home_first/home_prelude1"),
    ("the first version's homing, its steps not counted (`--arm home`)", "prelude_reset/homefree_prelude1"),
    ("`--home-first` now: the arm settled at home first (its steps counted)", "prelude_reset/settled_home_prelude1"),
)
# The episodes' list (every one's task and seed, a redrawn prelude's included) comes from this row's files.
EPISODE_LIST = "prelude_reset/reset_prelude1"
FROM_START = ("the same tasks from the start posture (no prelude)", "grounding_scenes/refit")
CHAIN_ROWS = (("the learned policy alone", "grounding_scenes/refit_chains20"),
              ("with `--home-first`", "prelude_reset/settled_home_chains20"))


def _load(root: Path, prefix: str, seed: int) -> dict:
    return json.loads((root / f"{prefix}_seed{seed}.json").read_text())


def episode_outcomes(root: Path, prefix: str) -> dict[tuple[str, int], bool]:
    """(task, episode seed) -> success, for every episode of the paired prelude runs (a failure is told by its seed)."""
    out = {}
    for seed in SEEDS:
        report = _load(root, prefix, seed)
        episodes = _load(root, EPISODE_LIST, seed)["episodes"]
        for task in TASKS:
            failed = {f["seed"] for f in report["tasks"][task]["failures"]}
            listed = [e["seed"] for e in episodes if e["task"] == task]
            if len(listed) != report["tasks"][task]["episodes"]:
                raise ValueError(f"{prefix} seed {seed}: {task} has {report['tasks'][task]['episodes']} episodes, "
                                 f"the episode list {len(listed)}")
            out.update({(task, s): s not in failed for s in listed})
    return out


def per_task(root: Path, prefix: str) -> list[int]:
    """Successes per task (TASKS' order), summed over SEEDS."""
    return [sum(_load(root, prefix, seed)["tasks"][task]["successes"] for seed in SEEDS) for task in TASKS]


def chain_lengths(root: Path, prefix: str) -> list[int]:
    """Tasks completed in each of the 80 chains, in seed then chain order (a chain with no failure did all 5)."""
    from trivla_drake.eval.episode import derive_seed

    lengths = []
    for seed in CHAIN_SEEDS:
        chains = _load(root, prefix, seed)["chains"]
        completed = {f["seed"]: f["completed"] for f in chains["failures"]}
        lengths += [completed.get(derive_seed(seed, "chain", k), 5) for k in range(CHAINS_PER_SEED)]
    return lengths


def tables(root: Path) -> str:
    lines = ["| run (every task after a one-task prelude, 72 episodes) | " + " | ".join(SHORT)
             + " | all | won / lost against the first row (McNemar p) |",
             "| --- |" + " --- |" * (len(SHORT) + 2)]
    first = episode_outcomes(root, PRELUDE_ROWS[0][1])
    for label, prefix in PRELUDE_ROWS:
        counts = per_task(root, prefix)
        paired = ""
        if prefix != PRELUDE_ROWS[0][1]:
            mine = episode_outcomes(root, prefix)
            won = sum(mine[k] and not first[k] for k in first)
            lost = sum(first[k] and not mine[k] for k in first)
            paired = f"{won} / {lost} (p {mcnemar_p(won, lost):.3f})"
        lines.append(f"| {label} | " + " | ".join(map(str, counts)) + f" | **{sum(counts)}** | {paired} |")
    counts = per_task(root, FROM_START[1])
    lines.append(f"| {FROM_START[0]} | " + " | ".join(map(str, counts)) + f" | **{sum(counts)}** | |")
    lines += ["", "| 80 chains (seeds 1003-1006) | Avg. Len ± stderr | chains reaching task 1 / 2 / 3 / 4 / 5 | "
              "paired by chain against the first row |", "| --- | --- | --- | --- |"]
    base = np.array(chain_lengths(root, CHAIN_ROWS[0][1]))
    for label, prefix in CHAIN_ROWS:
        lengths = np.array(chain_lengths(root, prefix))
        reach = " / ".join(str(sum(n >= k for n in lengths)) for k in range(1, 6))
        paired = ""
        if prefix != CHAIN_ROWS[0][1]:
            difference = lengths - base
            paired = (f"{difference.mean():+.2f} ± {stderr(difference):.2f} ({int((difference > 0).sum())} longer, "
                      f"{int((difference < 0).sum())} shorter)")
        lines.append(f"| {label} | {lengths.mean():.2f} ± {stderr(lengths):.2f} | {reach} | {paired} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", default=str(Path(__file__).resolve().parents[1]), help="the results folder")
    args = parser.parse_args(argv)
    print(tables(Path(args.root)), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
