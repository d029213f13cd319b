"""Success against the number of demonstrations (Table 1 bottom, as a curve), from stored evaluations.

    python results/data_efficiency/learning_curve.py [--seeds FIRST-LAST] OUT.png [LABEL=DEMOS=PREFIX ...]

reads PREFIX_seed1000.json ... PREFIX_seed1005.json (or FIRST ... LAST; `evaluate --episodes 2 --seed S --json`) for each arm
(without arms: the stored ones below), prints a markdown table (successes of all tasks, of the block tasks and of
the tasks whose target is fixed in the scene, each with its mean over seeds and standard error), the gain per
doubling of the demonstrations between consecutive arms, and the number of demonstrations at which the log-linear
trend through the last two arms would reach a given success rate. Draws the curve (log scale) into OUT.png.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "follow_control"))
from compare_seeds import SEEDS, first_file, parse_seeds, stderr  # noqa: E402 - a sibling results script, run as a file

# The drawer and the lamp stand where they always stand: these tasks need no block to be found.
FIXED_TARGET_TASKS = frozenset({"open_drawer", "close_drawer", "turn_on_light", "turn_off_light"})
# Success per task that five tasks in a row need for Avg. Len 3.5 (0.89 + 0.89^2 + ... + 0.89^5 = 3.57).
CHAIN_GOAL_RATE = 0.89

_HERE = "results/data_efficiency"
STORED_ARMS = (
    # label, demonstrations, prefix. Step 30's arm (96) and step 61's (288) train a fresh System 1 on the shipped
    # model's Systems 2 and 3 by the same three phases: step 30's stored six-seed files are its continuation (8200
    # steps in all; its 5700-step export scored 4 of 144 less), step 61 had 1200 steps (what fitted its session).
    # The 960 are the shipped model, whose System 1 trained far longer; rerun on the AMD EPYC kind step 61 ran on.
    # Step 61's arm has one seed so far (data30_seed1000.json): give it as an arm once it has the seeds asked for,
    # "30% (step 61)=288=results/data_efficiency/data30".
    ("10% (step 30, 8200 steps)", 96, f"{_HERE}/data10_longer"),
    ("100% (shipped)", 960, "results/prelude_stacked_mix/shipped"),
)


def successes_by_group(prefix: str, seeds: tuple[int, ...] = SEEDS) -> dict[str, np.ndarray]:
    """Each seed's success rate over all tasks, the block tasks and the fixed-target tasks."""
    groups: dict[str, list[float]] = {"all": [], "block": [], "fixed": []}
    for seed in seeds:
        path, candidates = first_file(prefix, f"_seed{seed}.json")
        if path is None:
            raise SystemExit(f"{' or '.join(map(str, candidates))}: no such evaluation (expected one file per seed "
                             f"{seeds[0]}-{seeds[-1]})")
        tasks = json.loads(path.read_text())["tasks"]
        for group, names in (("all", set(tasks)), ("block", set(tasks) - FIXED_TARGET_TASKS),
                             ("fixed", set(tasks) & FIXED_TARGET_TASKS)):
            done = sum(tasks[name]["successes"] for name in names)
            tried = sum(tasks[name]["episodes"] for name in names)
            groups[group].append(done / tried)
    return {group: np.array(rates) for group, rates in groups.items()}


def gain_per_doubling(demos: tuple[int, int], rates: tuple[float, float]) -> float:
    """Success gained per doubling of the demonstrations between two arms."""
    return (rates[1] - rates[0]) / math.log2(demos[1] / demos[0])


def demos_for(rate: float, demos: tuple[int, int], rates: tuple[float, float]) -> float:
    """Demonstrations at which the log-linear trend through two arms reaches `rate` (inf where it does not rise)."""
    slope = gain_per_doubling(demos, rates)
    return math.inf if slope <= 0 else demos[1] * 2 ** ((rate - rates[1]) / slope)


def parse_arm(text: str) -> tuple[str, int, str]:
    """`LABEL=DEMOS=PREFIX` -> (label, demonstrations, prefix)."""
    parts = text.split("=", 2)
    if len(parts) != 3 or not parts[1].isdigit() or int(parts[1]) <= 0:
        raise SystemExit(f"arm: expected LABEL=DEMOS=PREFIX with DEMOS a positive count, got {text!r}")
    return parts[0], int(parts[1]), parts[2]


def main(argv: list[str]) -> None:
    seeds = SEEDS
    if argv[:1] == ["--seeds"]:
        if len(argv) < 2:
            raise SystemExit(__doc__)
        seeds, argv = parse_seeds(argv[1]), argv[2:]
    if not argv:
        raise SystemExit(__doc__)
    out = Path(argv[0])
    arms = [parse_arm(arg) for arg in argv[1:]] or list(STORED_ARMS)
    if [demos for _, demos, _ in arms] != sorted({demos for _, demos, _ in arms}):
        raise SystemExit("arms: give them in rising, distinct numbers of demonstrations")
    loaded = [(label, demos, successes_by_group(prefix, seeds)) for label, demos, prefix in arms]

    print(f"| arm | demonstrations | all 12 tasks | 8 block tasks | 4 fixed-target tasks |\n| --- | --- | --- | --- | --- |")
    for label, demos, groups in loaded:
        cells = " | ".join(f"{g.mean():.3f} ± {stderr(g):.3f}" for g in groups.values())
        print(f"| {label} | {demos} | {cells} |")
    print(f"\nSeeds {seeds[0]}-{seeds[-1]}, 2 episodes per task and seed (mean over seeds ± standard error).\n")
    print("| between | success gained per doubling (all / block tasks) |\n| --- | --- |")
    for (label0, demos0, groups0), (label1, demos1, groups1) in zip(loaded, loaded[1:]):
        gains = [gain_per_doubling((demos0, demos1), (groups0[g].mean(), groups1[g].mean())) for g in ("all", "block")]
        print(f"| {demos0} and {demos1} | {gains[0]:+.3f} / {gains[1]:+.3f} |")
    if len(loaded) >= 2:
        (_, demos0, groups0), (_, demos1, groups1) = loaded[-2], loaded[-1]
        needed = demos_for(CHAIN_GOAL_RATE, (demos0, demos1), (groups0["all"].mean(), groups1["all"].mean()))
        print(f"\nThe log-linear trend through the last two arms reaches {CHAIN_GOAL_RATE:.2f} a task (what five in a "
              f"row need for Avg. Len 3.5) at about {needed:,.0f} demonstrations: an extrapolation, not a measurement.")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    demos = [d for _, d, _ in loaded]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for group, label, marker in (("all", "all 12 tasks", "o"), ("block", "8 block tasks", "s"),
                                 ("fixed", "4 fixed-target tasks", "^")):
        means = [g[group].mean() for _, _, g in loaded]
        errors = [stderr(g[group]) for _, _, g in loaded]
        ax.errorbar(demos, means, yerr=errors, marker=marker, capsize=3, label=label)
    ax.axhline(CHAIN_GOAL_RATE, color="grey", linestyle="--", linewidth=1)
    ax.text(demos[0], CHAIN_GOAL_RATE + 0.015, f"{CHAIN_GOAL_RATE:.2f} a task: Avg. Len 3.5", color="grey", fontsize=8)
    ax.set_xscale("log")
    ax.set_xticks(demos, [str(d) for d in demos])
    ax.minorticks_off()
    ax.set_ylim(0, 1)
    ax.set_xlabel("demonstrations (log scale)")
    ax.set_ylabel(f"success rate (seeds {seeds[0]}-{seeds[-1]}, ± s.e.)")
    ax.set_title("Success against the number of demonstrations")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main(sys.argv[1:])
