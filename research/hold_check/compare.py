"""Chains run without a hold (`../demo_chains/`'s seeds 1003-1006, this folder's 1007-1010) against the same chains
run with `evaluate --hold-check 0.5`, counted as the predicates first hold and counting only successes that lasted
the hold.

    python results/hold_check/compare.py > results/hold_check/compare.md
"""

from __future__ import annotations

import functools
import importlib.util
import json
import sys
from pathlib import Path

HERE = Path(__file__).parent
SEEDS = tuple(range(1003, 1011))


@functools.lru_cache(maxsize=None)
def _sibling(relative: str):
    """Another results script, loaded from its file (they are run as files, not imported as a package)."""
    path = HERE.parent / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def sign_test(wins: int, losses: int) -> float:
    """Exact two-sided sign test over the chains that differ: `../follow_control/compare_seeds.py`'s McNemar p."""
    return _sibling("follow_control/compare_seeds.py").mcnemar_p(wins, losses)


def load_hold(folder: Path, seed: int) -> tuple[list[int], list[int], list[str]] | None:
    """Per chain: tasks done as the predicates first held, tasks in a row that lasted the hold; and the task whose
    success was the first not to last, in every chain that had one (None if the file is absent or from before the
    summary listed `completed_lasting`)."""
    path = folder / f"chains20_hold0.5_seed{seed}.json"
    if not path.is_file():
        return None
    chains = json.loads(path.read_text())["chains"]
    if "completed_lasting" not in chains:
        return None
    first, lasting = chains["completed"], chains["completed_lasting"]
    broke = [tasks[k] for tasks, k, n in zip(chains["tasks"], lasting, first) if k < n]
    return first, lasting, broke


def main(hold_folder: Path = HERE, plain_folder: Path = HERE.parent / "demo_chains") -> str:
    compare = _sibling("demo_chains/compare.py")
    mean_stderr = compare.mean_stderr

    def cell(values, signed=False):
        mean, stderr = mean_stderr(values)
        return f"{mean:+.2f} ± {stderr:.2f}" if signed else f"{mean:.2f} ± {stderr:.2f}"

    lines = ["| seeds | chains | no hold | with the hold, as first held | with the hold, lasting | "
             "paired: hold - no hold | longer / shorter with the hold (sign test p) | paired: lasting - first held | "
             "chains shortened by the hold check |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    pooled: dict[str, list[int]] = {"plain": [], "first": [], "lasting": []}
    broke: list[str] = []
    for seed in SEEDS:
        plain = compare.load(plain_folder, "harness", seed) or compare.load(hold_folder, "harness", seed)
        hold = load_hold(hold_folder, seed)
        if plain is None or hold is None:
            continue
        first, lasting, broken = hold
        broke += broken
        for key, values in (("plain", plain), ("first", first), ("lasting", lasting)):
            pooled[key] += values
        lines.append(_row(str(seed), plain, first, lasting, cell))
    if pooled["plain"]:
        lines.append(_row("**all**", pooled["plain"], pooled["first"], pooled["lasting"], cell))
        counts = {task: broke.count(task) for task in sorted(set(broke))}
        lines += ["", "The first success that did not last, per chain: "
                  + (", ".join(f"{task} {n}" for task, n in counts.items()) or "none")]
    return "\n".join(lines)


def _row(label, plain, first, lasting, cell) -> str:
    shortened = sum(a < b for a, b in zip(lasting, first))
    longer = sum(a > b for a, b in zip(first, plain))
    shorter = sum(a < b for a, b in zip(first, plain))
    return (f"| {label} | {len(plain)} | {cell(plain)} | {cell(first)} | {cell(lasting)} | "
            f"{cell([a - b for a, b in zip(first, plain)], True)} | {longer} / {shorter} (p {sign_test(longer, shorter):.2f}) | "
            f"{cell([a - b for a, b in zip(lasting, first)], True)} | {shortened} |")


def tasks_against_audit(hold_folder: Path = HERE, audit_folder: Path = HERE.parent / "predicate_audit") -> str:
    """`evaluate --hold-check 0.5` against the predicate audit's rows of the same episodes (base seeds with a
    `tasks_hold0.5_seed{S}.json` here): per task, successes and successes that lasted, in each."""
    from trivla_drake.eval.episode import derive_seed

    audit = {}
    for path in sorted(audit_folder.glob("shipped*_seeds1000-1017.json")):
        audit.update({(row["task"], row["seed"]): row for row in json.loads(path.read_text())["rows"]})
    lines = ["| seed | task | successes (evaluate / audit) | lasted the hold (evaluate / audit) |",
             "| --- | --- | --- | --- |"]
    for path in sorted(hold_folder.glob("tasks_hold0.5_seed*.json")):
        report = json.loads(path.read_text())
        base, episodes = report["seed"], report["episodes_per_task"]
        for task, row in report["tasks"].items():
            rows = [audit.get((task, derive_seed(base, task, i))) for i in range(episodes)]
            if None in rows:
                lines.append(f"| {base} | {task} | {row['successes']} / not in the audit | "
                             f"{row['lasting_successes']} / not in the audit |")
                continue
            won = sum(r["success"] for r in rows)
            lasted = sum(r.get("success_after_hold", False) for r in rows)
            lines.append(f"| {base} | {task} | {row['successes']} / {won} | {row['lasting_successes']} / {lasted} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(main(*(Path(a) for a in sys.argv[1:])))
    print()
    print(tasks_against_audit())
