"""Paired comparison of the two arms of research/minilm_closed_loop (recipe.yaml): success on the training templates and
on the held-out paraphrases, per arm and per task, and the paired differences (B - A, paraphrases - templates) with
standard errors over the (task, seed) cells; the shipped model's stored evaluations on the same seeds as a reference.

    python research/minilm_closed_loop/compare.py --run minilm_closed_loop_run --out research/minilm_closed_loop
"""
from __future__ import annotations

import argparse
import glob
import json
import math
from pathlib import Path

from trivla_drake.eval.paper_tables import stored_evaluation_path
from trivla_drake.tasks.suite import TASK_NAMES

SEEDS = (1000, 1001, 1002)
Cells = dict[tuple[str, int], tuple[int, int]]  # (task, base seed) -> (successes, episodes)


def journal_cells(folder: Path) -> Cells:
    """Successes per (task, base seed) in an evaluate run's episodes.jsonl."""
    cells: dict[tuple[str, int], list[int]] = {}
    with open(folder / "episodes.jsonl") as f:
        for line in f:
            row = json.loads(line)
            if "job" not in row:
                continue
            kind, task, _index, base_seed = row["job"]
            if kind != "episode":
                continue
            cell = cells.setdefault((task, base_seed), [0, 0])
            cell[0] += bool(row["result"]["success"])
            cell[1] += 1
    return {key: (s, n) for key, (s, n) in cells.items()}


def stored_cells(evaluations: Path, checkpoint: str, paraphrases: bool) -> Cells:
    """Successes per (task, base seed) in the stored single-seed evaluations (results/evaluations, written by
    `trivla-drake tables`) of `checkpoint` as it is now: a stored file is its own when its name is the key of this
    checkpoint's contents and its settings (older versions of the same folder are skipped)."""
    cells: Cells = {}
    for path in sorted(glob.glob(str(evaluations / "*.json"))):
        record = json.loads(Path(path).read_text())
        settings, result = record["settings"], record["result"]
        if (stored_evaluation_path(evaluations, checkpoint, settings).name != Path(path).name
                or settings.get("kind") != "evaluate"
                or bool(settings.get("paraphrases")) != paraphrases or settings.get("seed") not in SEEDS
                or settings.get("episodes") != 2):
            continue
        for task, row in result["tasks"].items():
            cells[(task, settings["seed"])] = (row["successes"], row["episodes"])
    return cells


def rate(cells: Cells) -> tuple[float, float]:
    """Pooled success rate and its binomial standard error."""
    s = sum(v[0] for v in cells.values())
    n = sum(v[1] for v in cells.values())
    p = s / n
    return p, math.sqrt(p * (1 - p) / n)


def paired(x: Cells, y: Cells) -> tuple[float, float, int]:
    """Mean over the shared (task, seed) cells of y's success rate minus x's, its standard error, and the cell count."""
    keys = sorted(set(x) & set(y))
    d = [y[k][0] / y[k][1] - x[k][0] / x[k][1] for k in keys]
    mean = sum(d) / len(d)
    var = sum((v - mean) ** 2 for v in d) / (len(d) - 1)
    return mean, math.sqrt(var / len(d)), len(d)


def per_task(cells: Cells, task: str) -> str:
    s = sum(v[0] for k, v in cells.items() if k[0] == task)
    n = sum(v[1] for k, v in cells.items() if k[0] == task)
    return f"{s}/{n}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default="minilm_closed_loop_run", help="the recipe's workdir")
    parser.add_argument("--evaluations", default="results/evaluations", help="the shipped model's stored evaluations")
    parser.add_argument("--out", default="research/minilm_closed_loop", help="where figures.json and the plot go")
    args = parser.parse_args()
    run = Path(args.run)
    arms = {
        "shipped (960 demos, full recipe)": (stored_cells(Path(args.evaluations), "models/trivla_cpu", False),
                                             stored_cells(Path(args.evaluations), "models/trivla_cpu", True)),
        "A: from-scratch tokens": (journal_cells(run / "eval/a_tasks"), journal_cells(run / "eval/a_paraphrases")),
        "B: frozen MiniLM": (journal_cells(run / "eval/b_tasks"), journal_cells(run / "eval/b_paraphrases")),
    }
    figures: dict = {"arms": {}, "per_task": {}}
    print("| arm | templates | paraphrases | paraphrases - templates (paired) |")
    print("| --- | --- | --- | --- |")
    for name, (templates, paraphrases) in arms.items():
        if not templates or not paraphrases:
            print(f"| {name} | (no evaluations found) | | |")
            continue
        (pt, st), (pp, sp) = rate(templates), rate(paraphrases)
        d, sd, n = paired(templates, paraphrases)
        figures["arms"][name] = {"templates": [pt, st], "paraphrases": [pp, sp], "paraphrase_drop": [d, sd, n]}
        print(f"| {name} | {pt:.2f} ± {st:.2f} | {pp:.2f} ± {sp:.2f} | {d:+.2f} ± {sd:.2f} ({n} cells) |")
    (a_t, a_p), (b_t, b_p) = arms["A: from-scratch tokens"], arms["B: frozen MiniLM"]
    print()
    for label, x, y in (("templates", a_t, b_t), ("paraphrases", a_p, b_p)):
        d, sd, n = paired(x, y)
        figures[f"b_minus_a_{label}"] = [d, sd, n]
        print(f"B - A on {label}: {d:+.3f} ± {sd:.3f} over {n} (task, seed) cells")
    print()
    print("| task | " + " | ".join(f"{name} templates / paraphrases" for name in arms) + " |")
    print("| --- |" + " --- |" * len(arms))
    for task in TASK_NAMES:
        row = [f"{per_task(t, task)} / {per_task(p, task)}" for t, p in arms.values()]
        figures["per_task"][task] = row
        print(f"| {task} | " + " | ".join(row) + " |")
    out = Path(args.out)
    (out / "figures.json").write_text(json.dumps(figures, indent=1) + "\n")
    plot(figures["arms"], out / "paraphrases.png")


def plot(arms: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    names = list(arms)
    for i, name in enumerate(names):
        for j, (key, colour) in enumerate((("templates", "tab:blue"), ("paraphrases", "tab:orange"))):
            p, se = arms[name][key]
            ax.bar(i + (j - 0.5) * 0.38, p, 0.36, yerr=se, color=colour, capsize=3,
                   label=key if i == 0 else None)
    ax.set_xticks(range(len(names)), names, fontsize=8)
    ax.set_ylabel("success (12 tasks, seeds 1000-1002)")
    ax.set_ylim(0, 1)
    ax.legend()
    ax.set_title("Held-out paraphrases: System 2 reading from-scratch tokens or the frozen MiniLM", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
