"""results/prelude_reset/reset_after_prelude.py: the tasks after a chain prelude, restarted in the scene the prelude
left. Its episodes must be `evaluate --prelude 1`'s (same prelude, task and instruction: the comparison is paired),
and the restarted scene must be the one the prelude left, with the arm in its start posture."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "results" / "prelude_reset" / "reset_after_prelude.py"


def _script():
    spec = importlib.util.spec_from_file_location("reset_after_prelude", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_restarted_episode_is_evaluates_episode_and_starts_in_the_scene_the_prelude_left():
    from trivla_drake.eval.episode import derive_seed, run_episode, shared_env
    from trivla_drake.tasks.oracle import OraclePolicy

    script = _script()
    row = script.run_reset_episode("oracle", "turn_on_light", 1000, 0, "start")
    stored = run_episode("turn_on_light", derive_seed(1000, "turn_on_light", 0), OraclePolicy(), prelude=1,
                         prelude_policy=OraclePolicy())
    assert (row["seed"], tuple(row["prelude"]), row["instruction"]) == (stored.seed, stored.prelude, stored.instruction)
    assert row["success"] and row["startable"]
    assert len(row["target_offset_cm"]) == 3
    # After the restart the blocks lie where the prelude left them, and the arm is in its start posture, still.
    env = shared_env(224)
    scene = env.scene()
    again = script.scene_spec_after(scene, scene.arm_q)
    for colour, block in again.blocks.items():
        np.testing.assert_allclose(block.position, scene.block_position(colour), atol=1e-9)
    restarted = env.reset(again)
    assert restarted["time"] == 0.0 and np.allclose(restarted["state"][9:], 0.0)
    for colour in again.blocks:
        np.testing.assert_allclose(env.scene().block_position(colour), scene.block_position(colour), atol=2e-3)


def _handover():
    spec = importlib.util.spec_from_file_location("handover_check", SCRIPT.parent / "handover_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_handover_check_measures_the_first_versions_hand_over_and_summarises_it():
    script = _handover()
    rows = script.handover_states(False, tasks=("turn_on_light",), episodes=1)
    assert len(rows) == 1 and rows[0]["steps"] > 0 and rows[0]["prelude"]
    # The first version hands over with the arm still moving (the state the fix waits out).
    assert rows[0]["joint_speed"] > 0.2
    line = script.summary_line("x", [{"to_home_cm": 1.0, "joint_speed": 0.5, "steps": 40},
                                     {"to_home_cm": 3.0, "joint_speed": 1.5, "steps": 60},
                                     {"to_home_cm": 9.0, "joint_speed": 0.7, "steps": 50}])
    assert line == "| x | 3 | 3.0 (1.0–9.0) | 0.70 (0.50–1.50) | 50 (40–60) |"
