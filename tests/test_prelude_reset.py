"""results/prelude_reset/reset_after_prelude.py: the tasks after a chain prelude, restarted in the scene the prelude
left. Its episodes must be `evaluate --prelude 1`'s (same prelude, task and instruction: the comparison is paired),
and the restarted scene must be the one the prelude left (blocks, drawer, lamp), with the arm in the episode's start
posture or where the prelude left it, still, and the hand open."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def script(results_script):
    return results_script("prelude_reset/reset_after_prelude.py")


def test_a_restarted_episode_is_evaluates_episode(script):
    from trivla_drake.eval.episode import derive_seed, run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    row = script.run_reset_episode("oracle", "turn_on_light", 1000, 0, "start")
    stored = run_episode("turn_on_light", derive_seed(1000, "turn_on_light", 0), OraclePolicy(), prelude=1,
                         prelude_policy=OraclePolicy())
    assert (row["seed"], tuple(row["prelude"]), row["instruction"]) == (stored.seed, stored.prelude, stored.instruction)
    assert row["success"] and row["startable"] and len(row["target_offset_cm"]) == 3


def _after_a_prelude(env, task_name="push_block_left", seed=1000):
    """The env after `evaluate --prelude 1`'s first episode's prelude of `task_name`: (obs, the episode's spec)."""
    from trivla_drake.eval.episode import _run_prelude, derive_seed
    from trivla_drake.tasks.chains import prelude_task
    from trivla_drake.tasks.oracle import OraclePolicy
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    episode_seed = derive_seed(seed, task_name, 0)
    spec, _ = sample_task_instance(get_task(task_name), np.random.default_rng(episode_seed), env.layout())
    obs = env.reset(spec)
    obs, _, done, why = _run_prelude(env, obs, OraclePolicy(), task_name, 1,
                                     np.random.default_rng(derive_seed(episode_seed, "prelude")), False, prelude_task)
    assert done and not why
    return obs, spec


def test_the_restart_keeps_the_scene_the_prelude_left_and_puts_the_arm_where_asked(script):
    from trivla_drake.eval.episode import shared_env

    env = shared_env(224)
    for arm in ("start", "prelude"):
        obs, spec = _after_a_prelude(env)
        left = env.scene()
        assert np.linalg.norm(left.arm_q - np.asarray(spec.arm_q)) > 0.05  # the prelude moved the arm
        restarted, steps = script.restart_after_prelude(env, obs, spec.arm_q, arm)
        now = env.scene()
        assert steps is None and restarted["time"] == 0.0 and np.allclose(restarted["state"][9:], 0.0)
        for colour in left.blocks:
            np.testing.assert_allclose(now.block_position(colour), left.block_position(colour), atol=2e-3)
        assert now.drawer_opening == pytest.approx(left.drawer_opening, abs=1e-3) and now.lamp_on == left.lamp_on
        expected = np.asarray(spec.arm_q) if arm == "start" else left.arm_q
        np.testing.assert_allclose(now.arm_q, expected, atol=1e-6)
        assert now.finger_width > 0.07  # the hand opened
    with pytest.raises(ValueError, match="arm"):
        script.restart_after_prelude(env, obs, spec.arm_q, "elsewhere")


def test_the_handover_check_measures_the_first_versions_hand_over_and_summarises_it(results_script):
    script = results_script("prelude_reset/handover_check.py")
    rows = script.handover_states(False, tasks=("turn_on_light",), episodes=1)
    assert len(rows) == 1 and rows[0]["steps"] > 0 and rows[0]["prelude"]
    # The first version hands over with the arm still moving (the state the fix waits out).
    assert rows[0]["joint_speed"] > 0.2
    line = script.summary_line("x", [{"to_home_cm": 1.0, "joint_speed": 0.5, "steps": 40},
                                     {"to_home_cm": 3.0, "joint_speed": 1.5, "steps": 60},
                                     {"to_home_cm": 9.0, "joint_speed": 0.7, "steps": 50}])
    assert line == "| x | 3 | 3.0 (1.0–9.0) | 0.70 (0.50–1.50) | 50 (40–60) |"
