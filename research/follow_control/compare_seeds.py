"""Compare models evaluated on the same seeds (`evaluate --episodes 2 --seed S --json`, one file per seed).

    python results/follow_control/compare_seeds.py [--seeds FIRST-LAST] [--chain-seeds FIRST-LAST] OUT.png
        LABEL=PREFIX [LABEL=PREFIX ...]

reads PREFIX_seed1000.json ... PREFIX_seed1005.json (or FIRST ... LAST) for each model (PREFIX may be several,
joined by "+", where a model's seeds were evaluated into different folders: each seed's file is taken from the
first that has it) and prints a markdown table: successes per
task, the total, the mean over seeds with its standard error, and, against the first model, the per-seed
difference (paired by seed, since each seed's scenes are the same for every model) and the episodes won and lost
(an episode is one scene, instruction and policy seed, the same for every model) with the exact McNemar p-value of
that split. It draws the per-task successes as grouped bars into OUT.png. Models that also have
PREFIX_chains20_seed1003.json and ..._seed1004.json (`evaluate --episodes 0 --chains 20`) get a second table: Avg.
Len over those 40 chains, and each model's difference to the first such model paired chain by chain (the chains of
a seed are the same for every model); `--chain-seeds 1003-1006` reads those four seeds' chains (80) instead.
"""

import json
import math
import sys
from pathlib import Path

import numpy as np

SEEDS = tuple(range(1000, 1006))


def first_file(prefix: str, suffix: str) -> tuple[Path | None, list[Path]]:
    """The first existing PREFIX + suffix of the "+"-joined prefixes (None if there is none), and every candidate."""
    candidates = [Path(f"{one}{suffix}") for one in prefix.split("+")]
    return next((path for path in candidates if path.is_file()), None), candidates


def load(prefix: str, seeds: tuple[int, ...] = SEEDS) -> tuple[dict[str, int], np.ndarray, set[tuple[int, str, int]]]:
    """Successes per task over the seeds, each seed's average success, and the failed episodes as (evaluation
    seed, task, episode seed)."""
    per_task: dict[str, int] = {}
    averages = []
    failed = set()
    for seed in seeds:
        path, candidates = first_file(prefix, f"_seed{seed}.json")
        if path is None:
            raise SystemExit(f"{' or '.join(map(str, candidates))}: no such evaluation (expected one file per seed "
                             f"{seeds[0]}-{seeds[-1]})")
        result = json.loads(path.read_text())
        averages.append(result["average_success"])
        for task, row in result["tasks"].items():
            per_task[task] = per_task.get(task, 0) + row["successes"]
            failed.update((seed, task, failure["seed"]) for failure in row["failures"])
    return per_task, np.array(averages), failed


CHAIN_SEEDS = (1003, 1004)


def mcnemar_p(won: int, lost: int) -> float:
    """Exact two-sided McNemar test: the chance of a split at least this uneven among won + lost episodes if
    each of them were a coin flip between the two models."""
    n = won + lost
    return min(1.0, 2 * sum(math.comb(n, k) for k in range(min(won, lost) + 1)) / 2 ** n) if n else 1.0


def stderr(values: np.ndarray) -> float:
    return float(values.std(ddof=1) / np.sqrt(len(values)))


def load_chains(prefix: str, chain_seeds: tuple[int, ...] = CHAIN_SEEDS
                ) -> tuple[dict[tuple[int, int], int], int, int] | None:
    """Tasks completed by each chain that stopped early, keyed by (evaluation seed, chain seed); the number of
    chains; and a chain's length (from the first of the "+"-joined prefixes with a file). None where the chain
    files are missing."""
    stopped: dict[tuple[int, int], int] = {}
    count = 0
    for seed in chain_seeds:
        path, _ = first_file(prefix, f"_chains20_seed{seed}.json")
        if path is None:
            return None
        chains = json.loads(path.read_text())["chains"]
        count += chains["count"]
        length = len(chains["completed_at_least"])
        stopped.update({(seed, failure["seed"]): failure["completed"] for failure in chains["failures"]})
    return stopped, count, length


def chain_lengths(models: dict[str, tuple[dict, int, int]]) -> dict[str, np.ndarray]:
    """Each model's tasks completed per chain, in one chain order for all: a chain no model stopped early
    completed all tasks in every model, so it adds the full length to each (and nothing to the differences)."""
    keys = sorted(set().union(*(stopped for stopped, _, _ in models.values())))
    shapes = {(count, length) for _, count, length in models.values()}
    if len(shapes) != 1:
        raise SystemExit(f"the chain evaluations differ in their number of chains or tasks per chain: {sorted(shapes)}")
    (count, length), = shapes
    return {label: np.array([stopped.get(key, length) for key in keys] + [length] * (count - len(keys)), dtype=float)
            for label, (stopped, _, _) in models.items()}


def parse_seeds(text: str, option: str = "--seeds") -> tuple[int, ...]:
    """`FIRST-LAST` -> (FIRST, ..., LAST)."""
    first, _, last = text.partition("-")
    if not (first.isdigit() and last.isdigit() and int(first) <= int(last)):
        raise SystemExit(f"{option}: expected FIRST-LAST (e.g. 1006-1011), got {text!r}")
    return tuple(range(int(first), int(last) + 1))


def main(argv: list[str]) -> None:
    seeds, chain_seeds = SEEDS, CHAIN_SEEDS
    while argv[:1] in (["--seeds"], ["--chain-seeds"]):
        if len(argv) < 2:
            raise SystemExit(__doc__)
        if argv[0] == "--seeds":
            seeds = parse_seeds(argv[1])
        else:
            chain_seeds = parse_seeds(argv[1], "--chain-seeds")
        argv = argv[2:]
    if len(argv) < 2 or any("=" not in arg for arg in argv[1:]):
        raise SystemExit(__doc__)
    out, models = Path(argv[0]), [arg.split("=", 1) for arg in argv[1:]]
    loaded = {label: load(prefix, seeds) for label, prefix in models}
    tasks = list(next(iter(loaded.values()))[0])
    _, first, first_failed = next(iter(loaded.values()))
    print("| model | " + " | ".join(tasks) + " | all | mean ± stderr | paired difference to the first | "
          "episodes won / lost against the first (McNemar p) |")
    print("| --- " * (len(tasks) + 5) + "|")
    for i, (label, (per_task, averages, failed)) in enumerate(loaded.items()):
        difference = averages - first
        paired = "-" if i == 0 else f"{difference.mean():+.3f} ± {stderr(difference):.3f}"
        won, lost = len(first_failed - failed), len(failed - first_failed)
        flips = "-" if i == 0 else f"{won} / {lost} ({mcnemar_p(won, lost):.2f})"
        print(f"| {label} | " + " | ".join(str(per_task[t]) for t in tasks) +
              f" | {sum(per_task.values())} | {averages.mean():.3f} ± {stderr(averages):.3f} | {paired} | {flips} |")

    chains = {label: loaded_chains for label, prefix in models
              if (loaded_chains := load_chains(prefix, chain_seeds)) is not None}
    if chains:
        lengths = chain_lengths(chains)
        reference = next(iter(lengths.values()))
        print(f"\n| model | Avg. Len, {len(reference)} chains (seeds {', '.join(map(str, chain_seeds))}) | "
              "paired by chain to the first |\n| --- | --- | --- |")
        for i, (label, values) in enumerate(lengths.items()):
            paired = "-" if i == 0 else f"{(values - reference).mean():+.3f} ± {stderr(values - reference):.3f}"
            print(f"| {label} | {values.mean():.3f} ± {stderr(values):.3f} | {paired} |")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 4))
    x = np.arange(len(tasks))
    width = 0.8 / len(loaded)
    episodes = 2 * len(seeds)
    for i, (label, (per_task, _, _)) in enumerate(loaded.items()):
        ax.bar(x + (i - (len(loaded) - 1) / 2) * width, [per_task[t] for t in tasks], width,
               label=f"{label}: {sum(per_task.values())}/{episodes * len(tasks)}")
    ax.set_xticks(x, [t.replace("_", " ") for t in tasks], rotation=40, ha="right")
    ax.set_ylim(0, episodes + 0.5)
    ax.set_ylabel(f"successes of {episodes} (seeds {seeds[0]}-{seeds[-1]})")
    ax.legend(fontsize=8, ncol=min(4, len(loaded)), loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    print(f"\nplot: {out}")


if __name__ == "__main__":
    main(sys.argv[1:])
