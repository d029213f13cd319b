"""The oracle in simulation: every predicate is false at reset and true after the oracle's run;
chains; the action executor integrates exactly the actions it is given."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.eval.env import TabletopEnv
from trivla_drake.eval.episode import derive_seed, run_chain, run_episode
from trivla_drake.systems.action_executor import apply_action
from trivla_drake.tasks import TASK_NAMES, get_task
from trivla_drake.tasks.oracle import OraclePolicy
from trivla_drake.tasks.scene import sample_scene
from trivla_drake.tasks.suite import sample_task_instance


@pytest.mark.parametrize("name", TASK_NAMES)
def test_oracle_solves_each_task_and_the_predicate_was_false_at_reset(name):
    task = get_task(name)
    seed = derive_seed(11, name, 0)
    env = TabletopEnv()
    spec, instance = sample_task_instance(task, np.random.default_rng(seed), env.layout())
    env.reset(spec)
    initial = env.scene()
    assert not task.success(instance.params, initial, initial)
    # The episode runner draws the same scene from the same seed.
    result = run_episode(name, seed, OraclePolicy())
    assert result.instruction == instance.instruction
    assert result.success, result.reason
    assert 0 < result.steps < task.max_steps


def test_oracle_chain_runs_five_different_tasks():
    result = run_chain(derive_seed(0, "chain", 1), OraclePolicy())
    names = [s.task for s in result.subtasks]
    assert result.completed == 5, (names, result.reason)
    assert len(set(names)) == 5
    assert all(s.success for s in result.subtasks)


def test_executor_integrates_the_actions_exactly():
    env = TabletopEnv()
    obs = env.reset(sample_scene(np.random.default_rng(0), env.layout()))
    np.testing.assert_allclose(obs["ee_target"], obs["tcp_pose"], atol=1e-9)  # starts where the hand is
    X = obs["ee_target"]
    rng = np.random.default_rng(1)
    for _ in range(60):
        action = rng.uniform(-1, 1, 7) * [0.004, 0.004, 0.004, 0.02, 0.02, 0.02, 1.0]
        X, width = apply_action(X, action)
        obs = env.step(action)
        np.testing.assert_allclose(obs["ee_target"], X, atol=1e-12)
        assert obs["gripper_command"] == (1.0 if width > 0 else -1.0)
    for _ in range(54):  # zero actions hold the target; the arm settles on it
        obs = env.step(np.zeros(7))
    np.testing.assert_allclose(obs["ee_target"], X, atol=1e-12)
    np.testing.assert_allclose(obs["tcp_pose"][:3, 3], X[:3, 3], atol=3e-3)
    assert obs["state"].shape == (18,) and abs(obs["time"] - 114 / 36) < 1e-9


def test_env_tells_the_last_applied_action():
    env = TabletopEnv(image_size=None)
    with pytest.raises(RuntimeError, match="before reset"):
        env.last_action
    env.reset(sample_scene(np.random.default_rng(0), env.layout()))
    np.testing.assert_array_equal(env.last_action, np.zeros(7))
    action = np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])
    env.step(action, images=False)
    np.testing.assert_array_equal(env.last_action, action)
    env.last_action[0] = 5.0  # a copy
    assert env.last_action[0] == 0.01
