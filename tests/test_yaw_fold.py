"""results/grasp_yaw/yaw_fold.py: the grasping episodes' successes by the named block's yaw, from a stored report."""

import json
from pathlib import Path

import pytest

STORED = Path(__file__).resolve().parents[1] / "results" / "grounding_scenes" / "grasp_tasks_refit.json"


@pytest.fixture
def script(results_script):
    return results_script("grasp_yaw/yaw_fold.py")


def test_the_rebuilt_scenes_are_the_stored_episodes(script):
    report = json.loads(STORED.read_text())
    rows = script.episode_yaws(report)
    assert len(rows) == sum(t["episodes"] for t in report["tasks"].values())
    for name, task in report["tasks"].items():
        mine = [r for r in rows if r["task"] == name]
        # Every stored failure is one of the rebuilt episodes' seeds, so the successes add up as stored.
        assert {f["seed"] for f in task["failures"]} <= {r["seed"] for r in mine}
        assert sum(r["success"] for r in mine) == task["successes"]
    for r in rows:
        assert -45.0 <= r["block_deg"] < 45.0 and -45.0 <= r["off_deg"] < 45.0
        assert abs(r["hand_deg"]) < 40.0 and abs(r["turn_deg"]) <= 180.0  # the start posture's spread of the wrist


def test_the_bins_hold_every_episode_once_and_the_table_shows_them(script):
    rows = [{"task": "lift_block", "success": s, "off_deg": d, "block_deg": d, "turn_deg": 2 * d}
            for s, d in [(True, 3.0), (False, -14.9), (True, 20.0), (False, 44.9), (False, -45.0)]]
    assert script.binned(rows, "off_deg", script.FOLD_EDGES) == [(0, 15, 2, 1), (15, 30, 1, 1), (30, 38, 0, 0),
                                                                (38, 46, 2, 0)]
    assert script.binned(rows, "off_deg", script.FOLD_EDGES, task="stack_block")[0] == (0, 15, 0, 0)
    table = script.markdown(rows)
    assert "| 0-15 | 1 / 2 | 1 / 2 |" in table and "| 60-180.1 | 0 / 2 |" in table
