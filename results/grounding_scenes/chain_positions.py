"""Where chains break: success at each chain position, pooled over `evaluate --chains` reports.

python results/grounding_scenes/chain_positions.py REPORT.json [...]

Each report's `chains.by_position` (evaluate, session 46) counts the chains that tried a k-th task and did it;
this sums them over the reports and lists the tasks that failed at each position. Reports made before
session 46 have no `by_position` and are refused by name."""

import json
import sys
from collections import Counter
from pathlib import Path


def pool(reports: dict[str, dict]) -> list[dict]:
    """Per position: tried, succeeded and the failed tasks (a Counter), summed over `reports` (name -> report)."""
    rows = [{"position": k + 1, "tried": 0, "succeeded": 0, "failed": Counter()} for k in range(5)]
    for name, report in reports.items():
        positions = report.get("chains", {}).get("by_position")
        if positions is None:
            raise ValueError(f"{name}: no chains.by_position (a chains report of evaluate from session 46 on)")
        for row, got in zip(rows, positions):
            row["tried"] += got["tried"]
            row["succeeded"] += got["succeeded"]
            row["failed"].update(got["failed_tasks"])
    return rows


def markdown(rows: list[dict], chains: int) -> str:
    avg_len = sum(r["succeeded"] for r in rows) / chains if chains else 0.0
    lines = [f"{chains} chains, Avg. Len {avg_len:.2f}", "",
             "| position | tried | succeeded | rate | failed tasks |", "| --- | --- | --- | --- | --- |"]
    for r in rows:
        rate = f"{r['succeeded'] / r['tried']:.2f}" if r["tried"] else "-"
        failed = ", ".join(f"{task} {n}" for task, n in r["failed"].most_common()) or "-"
        lines.append(f"| {r['position']} | {r['tried']} | {r['succeeded']} | {rate} | {failed} |")
    return "\n".join(lines)


def main(paths: list[str]) -> str:
    if not paths:
        sys.exit(__doc__)
    reports = {p: json.loads(Path(p).read_text()) for p in paths}
    rows = pool(reports)
    return markdown(rows, sum(r["chains"]["count"] for r in reports.values()))


if __name__ == "__main__":
    print(main(sys.argv[1:]))
