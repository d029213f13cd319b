"""Paired comparison of two `trivla-drake demo --json` runs of the same tasks and seeds (the Drake diagram).

    python results/camera_frames/compare_demo.py DIR LABEL_A LABEL_B [SUFFIX ...]

reads DIR/{LABEL}_{task}{suffix}.json for each of the twelve tasks and each suffix (default: "" and "_b") and prints
a markdown table: successes per task for both, the total, the episodes won and lost by B against A (an episode is
one scene, instruction and policy seed, the same for both) with the exact McNemar p-value, and the median
real-time factor of each.
"""

import json
import sys
from pathlib import Path

from trivla_drake.tasks import TASK_NAMES

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "follow_control"))
from compare_seeds import mcnemar_p  # noqa: E402


def load(folder: Path, label: str, suffixes: list[str]) -> tuple[dict[str, list[bool]], list[float]]:
    """Each task's episode successes in order (over the suffixes), and each run's real-time factor."""
    outcomes, speeds = {}, []
    for task in TASK_NAMES:
        outcomes[task] = []
        for suffix in suffixes:
            report = json.loads((folder / f"{label}_{task}{suffix}.json").read_text())
            outcomes[task] += [bool(e["success"]) for e in report["episodes"]]
            speeds.append(report["realtime_factor"])
    return outcomes, speeds


def main(argv: list[str]) -> str:
    folder, a, b = Path(argv[0]), argv[1], argv[2]
    suffixes = argv[3:] or ["", "_b"]
    (first, speed_a), (second, speed_b) = load(folder, a, suffixes), load(folder, b, suffixes)
    lines = [f"| task | {a} | {b} | won / lost by {b} |", "| --- | --- | --- | --- |"]
    won_all = lost_all = 0
    for task in TASK_NAMES:
        if len(first[task]) != len(second[task]):
            raise ValueError(f"{task}: {len(first[task])} episodes for {a}, {len(second[task])} for {b}")
        won = sum(y and not x for x, y in zip(first[task], second[task]))
        lost = sum(x and not y for x, y in zip(first[task], second[task]))
        won_all, lost_all = won_all + won, lost_all + lost
        lines.append(f"| {task} | {sum(first[task])} / {len(first[task])} | {sum(second[task])} / "
                     f"{len(second[task])} | {won} / {lost} |")
    total = sum(len(v) for v in first.values())
    lines.append(f"| **all** | **{sum(map(sum, first.values()))} / {total}** | **{sum(map(sum, second.values()))} / "
                 f"{total}** | {won_all} / {lost_all} (McNemar p {mcnemar_p(won_all, lost_all):.2f}) |")
    speed_a, speed_b = sorted(speed_a)[len(speed_a) // 2], sorted(speed_b)[len(speed_b) // 2]
    lines += ["", f"Median real-time factor per run: {a} {speed_a:.2f}, {b} {speed_b:.2f}."]
    return "\n".join(lines)


if __name__ == "__main__":
    print(main(sys.argv[1:]))
