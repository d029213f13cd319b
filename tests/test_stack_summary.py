"""results/stack_destinations/summarise.py: the stack-episode summary of stack_destinations.py's files."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture
def script(results_script):
    return results_script("stack_destinations/summarise.py")


def _row(held, success=False, to_destination=0.10, to_other=0.20, nearer=0):
    row = {"seed": 1000, "index": 0, "instruction": "stack", "success": success, "held_chunks": held}
    if held:
        row.update(min_to_destination=to_destination, min_to_other=to_other, last_to_destination=to_destination,
                   last_to_other=to_other, subgoal_nearer_destination=nearer)
    return row


def test_counts_and_thresholds(tmp_path, capsys, script):
    path = tmp_path / "a.json"
    path.write_text(json.dumps([_row(0), _row(10, True, 0.029, 0.30, 8), _row(30, False, 0.031, 0.052, 7)]))
    script.main([f"model={path}"])
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ")[1].strip(" |")
            for line in capsys.readouterr().out.splitlines()[2:]}
    assert rows == {"named block picked up": "2", "chunks with it in hand": "40",
                    "... whose sub-goal is nearer the destination": "15 (38%)",
                    "block brought within 3 cm (xy) of the destination": "1",
                    "block brought within 5.3 cm of the *other* block": "1", "stacked": "1"}


def test_a_policy_without_grounding_has_no_subgoal_share_and_bad_arguments_print_the_usage(tmp_path, capsys, script):
    path = tmp_path / "a.json"
    path.write_text(json.dumps([_row(5, nearer=None)]))
    script.main([f"oracle={path}"])
    assert "| ... whose sub-goal is nearer the destination | - |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="LABEL=OUT.json"):
        script.main([str(path)])


def test_stack_destinations_records_where_the_oracle_leaves_the_block(results_script):
    """One oracle stack episode: the named block held on its way, released on the destination and left on it."""
    script = results_script("stack_destinations/stack_destinations.py")
    row = script.episode(("oracle", 1000, 0, None))
    assert row["success"] and row["held_chunks"] > 0
    assert row["min_to_destination"] < 0.01 < row["min_to_other"]
    assert row["subgoal_nearer_destination"] is None and row["subgoal_to_destination_median"] is None  # no grounding
    assert row["final_to_destination"] < 0.01 and row["final_height"] > 0.05 and not row["final_held"]
