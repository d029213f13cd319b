"""Where chains break: success at each chain position, pooled over `evaluate --chains` reports.

python results/grounding_scenes/chain_positions.py REPORT.json [...] [--expected LABEL=EVALUATE_REPORT,... ...]

Each report's `chains.by_position` (evaluate, session 46) counts the chains that tried a k-th task and did it;
this sums them over the reports and lists the tasks that failed at each position. Reports made before
session 46 have no `by_position` and are refused by name.

`--expected LABEL=A.json,B.json` (repeatable) adds, per position, the successes expected if each task tried
there succeeded at its rate in those `evaluate` reports (e.g. from the start posture, or after a one-task
prelude): whether a position fails more than its mix of tasks explains."""

import argparse
import json
from collections import Counter
from pathlib import Path

POSITIONS = 5


def pool(reports: dict[str, dict]) -> list[dict]:
    """Per position: tried, succeeded, the failed tasks and the tried tasks (Counters), summed over `reports`."""
    rows = [{"position": k + 1, "tried": 0, "succeeded": 0, "failed": Counter(), "tasks": Counter()}
            for k in range(POSITIONS)]
    for name, report in reports.items():
        chains = report.get("chains", {})
        if "by_position" not in chains:
            raise ValueError(f"{name}: no chains.by_position (a chains report of evaluate from session 46 on)")
        for row, got in zip(rows, chains["by_position"]):
            row["tried"] += got["tried"]
            row["succeeded"] += got["succeeded"]
            row["failed"].update(got["failed_tasks"])
        for tasks in chains["tasks"]:
            for row, task in zip(rows, tasks):
                row["tasks"][task] += 1
    return rows


def task_rates(reports: list[dict]) -> dict[str, float]:
    """Each task's success rate over `evaluate` reports (their per-task rows pooled)."""
    wins, runs = Counter(), Counter()
    for report in reports:
        for task, row in report["tasks"].items():
            wins[task] += row["successes"]
            runs[task] += row["episodes"]
    return {task: wins[task] / runs[task] for task in runs if runs[task]}


def expected(row: dict, rates: dict[str, float], label: str) -> float:
    missing = sorted(set(row["tasks"]) - set(rates))
    if missing:
        raise ValueError(f"--expected {label}: no episodes of {', '.join(missing)}")
    return sum(rates[task] * count for task, count in row["tasks"].items())


def markdown(rows: list[dict], chains: int, expectations: dict[str, dict[str, float]]) -> str:
    avg_len = sum(r["succeeded"] for r in rows) / chains if chains else 0.0
    extra = "".join(f" expected {label} |" for label in expectations)
    lines = [f"{chains} chains, Avg. Len {avg_len:.2f}", "",
             "| position | tried | succeeded | rate |" + extra + " failed tasks |",
             "| --- | --- | --- | --- |" + " --- |" * len(expectations) + " --- |"]
    for r in rows:
        rate = f"{r['succeeded'] / r['tried']:.2f}" if r["tried"] else "-"
        cells = "".join(f" {expected(r, rates, label):.1f} |" for label, rates in expectations.items())
        failed = ", ".join(f"{task} {n}" for task, n in r["failed"].most_common()) or "-"
        lines.append(f"| {r['position']} | {r['tried']} | {r['succeeded']} | {rate} |{cells} {failed} |")
    return "\n".join(lines)


def main(argv: list[str]) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="+")
    parser.add_argument("--expected", action="append", default=[], metavar="LABEL=A.json,B.json")
    args = parser.parse_args(argv)
    reports = {p: json.loads(Path(p).read_text()) for p in args.reports}
    expectations = {}
    for spec in args.expected:
        label, _, files = spec.partition("=")
        if not label or not files:
            parser.error(f"--expected takes LABEL=A.json[,B.json...], got {spec!r}")
        expectations[label] = task_rates([json.loads(Path(f).read_text()) for f in files.split(",")])
    rows = pool(reports)
    return markdown(rows, sum(r["chains"]["count"] for r in reports.values()), expectations)


if __name__ == "__main__":
    import sys

    print(main(sys.argv[1:]))
