"""Tables of `chain_lifts.py`'s traces: where a task fails in chains, what its scenes were, and how it failed.

    python results/chain_lifts/summarise.py lifts.json > lifts.md
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def _median(values, digits: int = 0) -> str:
    values = [v for v in values if v is not None]
    return f"{np.median(values):.{digits}f}" if values else "-"


def _held_mode(task: str) -> str:
    """The last failure mode: the block was held, but the task's end was not reached."""
    return "held the block, not lifted 10 cm" if task == "lift_block" else "held the block, not put down right"


def failure_mode(row: dict) -> str:
    """How a try went, judged within its task's budget."""
    if row["success"]:
        return "succeeded"
    if row["success_extended"]:
        return "succeeded after its budget"
    if row["first_close"] is None:
        return "never closed the gripper"
    if not row["ever_held"]:
        return "closed, never held the block"
    return _held_mode(row["task"])


def group_rows(rows: list[dict]) -> list[tuple[str, list[dict]]]:
    """The tries by where they start: single episodes (the start posture), then each chain position."""
    groups = [("single episodes, start posture", [r for r in rows if r["position"] == 0])]
    positions = sorted({r["position"] for r in rows if r["position"] > 0})
    groups += [(f"chain task {p}" + (" (not homed)" if p == 1 else ""), [r for r in rows if r["position"] == p])
               for p in positions]
    return [(label, group) for label, group in groups if group]


def stands(row: dict) -> str:
    """Where the block to pick up is as the task starts: on the table, on another block, or in the hand (a
    chain's lift before it left it there, 15 cm up or more)."""
    if row["start"]["base"] is not None:
        return "on another block"
    return "in the hand" if row["start"]["block"][2] > 0.09 else "on the table"


def close_above_centre_cm(row: dict) -> float | None:
    """The tool-centre point's height at the first close above the block's centre as the task started [cm]
    (the oracle closes 0.3 cm above it, wherever the block stands; this is where the hand was when the chunk
    that closes it was planned, up to 10 steps before)."""
    close = row["first_close"]
    return None if close is None else close["tcp_z_cm"] - 100 * row["start"]["block"][2]


def close_height_table(rows: list[dict]) -> list[str]:
    """Where the first close is, against the block, for a block on the table and one on another block."""
    lines = ["| the block stands | tried | succeeded | first close: tool-centre point above the block's centre [cm], "
             "median (range) |", "| --- | --- | --- | --- |"]
    for label in ("on the table", "on another block", "in the hand"):
        chosen = [r for r in rows if stands(r) == label]
        if not chosen:
            continue
        heights = [h for h in map(close_above_centre_cm, chosen) if h is not None]
        spread = f"{np.median(heights):+.1f} ({min(heights):+.1f} to {max(heights):+.1f})" if heights else "-"
        lines.append(f"| {label} | {len(chosen)} | {sum(r['success'] for r in chosen)} | {spread} |")
    return lines


def success_table(rows: list[dict], budget: int, extended: int) -> list[str]:
    lines = [f"| {rows[0]['task']} | tried | succeeded ({budget} steps) | within {extended} steps | homing steps, median | "
             "steps of the successes, median (max) | first close: x-y to the block [cm], median |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, group in group_rows(rows):
        wins = [r["steps"] for r in group if r["success"]]
        most = f" ({max(wins)})" if wins else ""
        lines.append(f"| {label} | {len(group)} | {sum(r['success'] for r in group)} | "
                     f"{sum(r['success_extended'] for r in group)} | {_median(r['homing_steps'] for r in group if r['position'] > 1)} | "
                     f"{_median(wins)}{most} | "
                     f"{_median([r['first_close']['xy_to_block_cm'] if r['first_close'] else None for r in group], 1)} |")
    return lines


def scene_table(rows: list[dict]) -> list[str]:
    """Success by what the scene at the lift's start was like."""
    features = (
        ("the block on another block", lambda r: stands(r) == "on another block"),
        ("the block on the table", lambda r: stands(r) == "on the table"),
        ("the block in the hand (after a lift)", lambda r: stands(r) == "in the hand"),
        ("another block within 10 cm", lambda r: r["start"]["nearest_other_m"] < 0.10),
        ("the drawer open (> 5 cm)", lambda r: r["start"]["drawer_opening"] > 0.05),
        ("the hand more than 30 deg off the block's faces", lambda r: abs(r["start"]["yaw_to_hand_deg"]) > 30),
    )
    lines = ["| the task's start | single episodes: succeeded / tried | in chains: succeeded / tried |",
             "| --- | --- | --- |"]
    for label, test in features:
        cells = []
        for group in ([r for r in rows if r["position"] == 0], [r for r in rows if r["position"] > 0]):
            chosen = [r for r in group if test(r)]
            cells.append(f"{sum(r['success'] for r in chosen)} / {len(chosen)}")
        lines.append(f"| {label} | {' | '.join(cells)} |")
    return lines


def mode_table(rows: list[dict]) -> list[str]:
    modes = ("succeeded", "succeeded after its budget", "never closed the gripper", "closed, never held the block",
             _held_mode(rows[0]["task"]))
    groups = (("single episodes", [r for r in rows if r["position"] == 0]),
              ("in chains", [r for r in rows if r["position"] > 0]))
    lines = ["| outcome | " + " | ".join(label for label, _ in groups) + " |",
             "| --- | " + " | ".join("---" for _ in groups) + " |"]
    for mode in modes:
        lines.append(f"| {mode} | " + " | ".join(str(sum(failure_mode(r) == mode for r in group))
                                                for _, group in groups) + " |")
    return lines


def episode_rows(rows: list[dict]) -> list[str]:
    lines = ["| chain (seed/index) | position | before | homing steps | outcome | steps | block on | "
             "first close: x-y [cm], height [cm], above the block's centre [cm] | closes | block's highest [cm] |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        if r["position"] == 0:
            continue
        close = r["first_close"]
        close_cell = (f"{close['xy_to_block_cm']:.1f}, {close['tcp_z_cm']:.1f}, {close_above_centre_cm(r):+.1f}"
                      if close else "-")
        before = ", ".join(t for t, *_ in r["before"]) or "-"
        lines.append(f"| {r['seed']}/{r['chain']} | {r['position']} | {before} | "
                     f"{r['homing_steps'] if r['position'] > 1 else '-'} | {failure_mode(r)} | {r['steps']} | "
                     f"{r['start']['base'] or stands(r).split()[-1]} | {close_cell} | {r['closes']} | {r['max_block_z_cm']:.1f} |")
    return lines


def summarise(report: dict) -> str:
    chains = report["chain_tasks"]
    reached = [r for r in chains if r["reached"]]
    rows = report["single_tasks"] + reached
    budget = rows[0]["budget"]
    extended = budget + report["budget_extra"]
    out = [f"{report['task']} in chains, rerun: {len(chains)}, of which {len(reached)} reached it on this machine; "
           f"{len(report['single_tasks'])} single episodes. Every one ran up to {extended} steps.", ""]
    out += success_table(rows, budget, extended) + [""] + mode_table(rows) + [""] + scene_table(rows) + [""]
    out += close_height_table(rows) + [""]
    out += episode_rows(reached)
    return "\n".join(out)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    print(summarise(json.loads(Path(argv[0]).read_text())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
