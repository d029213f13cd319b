"""Bar chart of the grounding checks (`probe --grounding-scenes 20`) in this folder: the median x-y error of the
sub-goal to the named block on the first frame and along the oracle's approach (far / mid / near), per grounding.

    python results/grounding_anchor/plot_checks.py   # -> results/grounding_anchor/grounding_checks.png
"""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent
GROUNDINGS = {"shipped": "shipped", "anchor_bind": "anchored: static view",
              "anchor_wrist_bind": "anchored: static + wrist views"}


def read_check(path: Path) -> dict[str, float]:
    """The medians [cm] of one check: 'first frame', then far / mid / near for the block approached."""
    text = path.read_text()
    medians = {"first frame": float(re.search(r"median ([\d.]+) cm from it", text).group(1))}
    for phase in ("far", "mid", "near"):
        medians[phase] = float(re.search(rf"{phase} \([^)]*\): \d+/\d+, ([\d.]+) cm", text).group(1))
    return medians


def main() -> None:
    checks = {label: read_check(HERE / f"grounding_check_{name}.md") for name, label in GROUNDINGS.items()}
    phases = list(next(iter(checks.values())))
    figure, axes = plt.subplots(figsize=(7.5, 3.6))
    width = 0.8 / len(checks)
    for i, (label, medians) in enumerate(checks.items()):
        xs = [p + (i - (len(checks) - 1) / 2) * width for p in range(len(phases))]
        bars = axes.bar(xs, [medians[p] for p in phases], width, label=label)
        axes.bar_label(bars, fmt="%.1f", fontsize=8)
    axes.set_xticks(range(len(phases)), ["first frame", "far (> 15 cm)", "mid (5-15 cm)", "near (0-5 cm)"])
    axes.set_ylabel("sub-goal to named block, median x-y [cm]")
    axes.set_title("Instruction grounding on 20 unseen lift scenes (probe --grounding-scenes 20)")
    axes.set_ylim(0, 3.7)
    axes.legend(fontsize=8, loc="upper center", ncols=3)
    figure.tight_layout()
    figure.savefig(HERE / "grounding_checks.png", dpi=120)


if __name__ == "__main__":
    main()
