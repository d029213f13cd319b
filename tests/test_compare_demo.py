"""results/camera_frames/compare_demo.py: two `demo --json` runs of the same tasks and seeds, paired by episode."""

from __future__ import annotations

import json

import pytest

from trivla_drake.tasks import TASK_NAMES


def _write(folder, label, suffix, successes, speed):
    for task in TASK_NAMES:
        episodes = [{"task": task, "success": s} for s in successes.get(task, [False, False])]
        (folder / f"{label}_{task}{suffix}.json").write_text(json.dumps({"episodes": episodes, "realtime_factor": speed}))


def test_per_task_counts_won_lost_and_speed(tmp_path, results_script):
    script = results_script("camera_frames/compare_demo.py")
    _write(tmp_path, "old", "", {"lift_block": [True, False]}, 0.8)
    _write(tmp_path, "new", "", {"lift_block": [False, True], "open_drawer": [True, True]}, 1.2)
    _write(tmp_path, "old", "_b", {}, 0.8)
    _write(tmp_path, "new", "_b", {}, 1.2)
    table = script.main([str(tmp_path), "old", "new"])
    assert "| lift_block | 1 / 4 | 1 / 4 | 1 / 1 |" in table
    assert "| open_drawer | 0 / 4 | 2 / 4 | 2 / 0 |" in table
    assert f"| **all** | **1 / {4 * len(TASK_NAMES)}** | **3 / {4 * len(TASK_NAMES)}** | 3 / 1 (McNemar p 0.62) |" in table
    assert "old 0.80, new 1.20" in table
    (tmp_path / "new_stack_block_b.json").write_text(json.dumps({"episodes": [], "realtime_factor": 1.0}))
    with pytest.raises(ValueError, match="stack_block: 4 episodes for old, 2 for new"):
        script.main([str(tmp_path), "old", "new"])
