"""The stack-episode summary table of the READMEs, from `stack_destinations.py`'s JSON files:

    python results/stack_destinations/summarise.py LABEL=OUT.json [LABEL=OUT.json ...]

one column per file: episodes whose named block was picked up (held in at least one chunk), the chunks with it in
hand, those whose sub-goal lies nearer the destination, episodes that brought it within 3 cm (xy) of the
destination and within 5.3 cm of the other block, and episodes stacked."""

import json
import sys
from pathlib import Path

NEAR_DESTINATION_M = 0.03
NEAR_OTHER_M = 0.053


def summary(rows: list[dict]) -> dict[str, str]:
    held = [r for r in rows if r["held_chunks"]]
    chunks = sum(r["held_chunks"] for r in held)
    nearer = [r["subgoal_nearer_destination"] for r in held]
    return {
        "named block picked up": str(len(held)),
        "chunks with it in hand": str(chunks),
        "... whose sub-goal is nearer the destination": "-" if None in nearer or not chunks else
        f"{sum(nearer)} ({100 * sum(nearer) / chunks:.0f}%)",
        "block brought within 3 cm (xy) of the destination": str(sum(r["min_to_destination"] < NEAR_DESTINATION_M
                                                                     for r in held)),
        "block brought within 5.3 cm of the *other* block": str(sum(r["min_to_other"] < NEAR_OTHER_M for r in held)),
        "stacked": str(sum(r["success"] for r in rows)),
    }


def main(argv: list[str]) -> None:
    if not argv or any("=" not in arg for arg in argv):
        raise SystemExit(__doc__)
    files = {label: json.loads(Path(path).read_text()) for label, path in (arg.split("=", 1) for arg in argv)}
    columns = {label: summary(rows) for label, rows in files.items()}
    episodes = {len(rows) for rows in files.values()}
    print(f"| stack episodes ({'/'.join(map(str, sorted(episodes)))}) | " + " | ".join(columns) + " |")
    print("| --- " * (len(columns) + 1) + "|")
    for row in next(iter(columns.values())):
        print(f"| {row} | " + " | ".join(column[row] for column in columns.values()) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
