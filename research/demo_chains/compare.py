"""The same 5-task chains run through the Drake diagram (`demo --chains`) and the evaluation harness
(`evaluate --chains`), paired chain by chain (chain j of a seed starts from the same scene and first task in both).

    python results/demo_chains/compare.py results/demo_chains > results/demo_chains/compare.md
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path


def load(folder: Path, prefix: str, seed: int) -> list[int] | None:
    """Tasks completed per chain, in chain order, in `folder/{prefix}_chains20_seed{seed}.json` (None if absent)."""
    path = folder / f"{prefix}_chains20_seed{seed}.json"
    if not path.is_file() or path.stat().st_size == 0:
        return None
    report = json.loads(path.read_text())
    if "chain_runs" in report:  # demo --chains
        return [c["completed"] for c in report["chain_runs"]]
    if "completed" in report["chains"]:
        return report["chains"]["completed"]
    # evaluate's reports before session 66: a chain listed among the failures completed what it says there, the
    # others all their tasks.
    from trivla_drake.eval.episode import derive_seed

    failed = {f["seed"]: f["completed"] for f in report["chains"]["failures"]}
    return [failed.get(derive_seed(seed, "chain", j), len(tasks)) for j, tasks in enumerate(report["chains"]["tasks"])]


def mean_stderr(values: list[int]) -> tuple[float, float]:
    n = len(values)
    mean = sum(values) / n
    var = sum((v - mean) ** 2 for v in values) / (n - 1) if n > 1 else 0.0
    return mean, math.sqrt(var / n)


def main(folder: str) -> str:
    folder = Path(folder)
    lines = ["| seeds | chains | Drake diagram (`demo --chains`) | harness (`evaluate --chains`) | paired difference | "
             "longer / shorter in the diagram |", "| --- | --- | --- | --- | --- | --- |"]
    all_demo, all_harness = [], []
    for seed in (1003, 1004, 1005, 1006):
        demo, harness = load(folder, "demo", seed), load(folder, "harness", seed)
        if demo is None or harness is None:
            continue
        all_demo += demo
        all_harness += harness
        lines.append(_row(str(seed), demo, harness))
    if all_demo:
        lines.append(_row("**all**", all_demo, all_harness))
    return "\n".join(lines)


def _row(label: str, demo: list[int], harness: list[int]) -> str:
    d, h = mean_stderr(demo), mean_stderr(harness)
    diff = mean_stderr([a - b for a, b in zip(demo, harness)])
    longer = sum(a > b for a, b in zip(demo, harness))
    shorter = sum(a < b for a, b in zip(demo, harness))
    return (f"| {label} | {len(demo)} | {d[0]:.2f} ± {d[1]:.2f} | {h[0]:.2f} ± {h[1]:.2f} | "
            f"{diff[0]:+.2f} ± {diff[1]:.2f} | {longer} / {shorter} |")


if __name__ == "__main__":
    print(main(sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).parent)))
