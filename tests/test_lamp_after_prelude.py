"""results/grounding_scenes/lamp_after_prelude.py: lamp presses after a prelude chosen on purpose."""

import math

import numpy as np
import pytest

from trivla_drake.tasks.scene import Layout, scene_from_spec, yaw_rotation
from trivla_drake.tasks.suite import TASKS, get_task, sample_task_instance


@pytest.fixture
def script(results_script):
    return results_script("grounding_scenes/lamp_after_prelude.py")


def test_the_forced_prelude_draws_only_its_task_and_only_where_it_can_run(script):
    layout = Layout.default()
    spec, _ = sample_task_instance(get_task("turn_on_light"), np.random.default_rng(1), layout)
    scene = scene_from_spec(spec, layout)
    draw = script.forced_prelude("open_drawer" if TASKS["open_drawer"].candidates(scene) else "close_drawer")
    got = draw(scene, np.random.default_rng(0), exclude={"turn_on_light"})
    assert got.task in ("open_drawer", "close_drawer") and got.instruction
    assert draw(scene, np.random.default_rng(0), exclude={got.task}) is None  # excluded: nothing else is drawn
    scene.drawer_opening = 0.0 if got.task == "close_drawer" else 0.15  # open: nothing to open; shut: to close
    assert script.forced_prelude(got.task)(scene, np.random.default_rng(0), set()) is None  # cannot run there


def test_the_yaw_is_measured_off_the_press_modulo_a_half_turn_at_the_first_chunk(script):
    class Inner:
        def reset(self, instruction, seed):
            pass

        def act(self, observation):
            return np.zeros((1, 7))

    spy = script._YawAtStart(Inner())
    spy.reset("turn on the light", 0)
    pose = np.eye(4)
    pose[:3, :3] = yaw_rotation(math.radians(170.0))  # 10 degrees off, the fingers being alike
    spy.act({"tcp_pose": pose})
    pose[:3, :3] = yaw_rotation(math.radians(45.0))
    spy.act({"tcp_pose": pose})  # later chunks do not count
    assert spy.yaw_off == pytest.approx(10.0)
    spy.reset("turn off the light", 1)
    assert spy.yaw_off is None


def test_the_table_counts_each_prelude_and_leaves_out_episodes_without_one(script):
    rows = [{"prelude": "open_drawer", "task": "turn_on_light", "success": True, "yaw_off_deg": 0.0,
             "ran_prelude": ["open_drawer"]},
            {"prelude": "open_drawer", "task": "turn_off_light", "success": False, "yaw_off_deg": 2.0,
             "ran_prelude": ["open_drawer"]},
            {"prelude": "open_drawer", "task": "turn_off_light", "success": True, "yaw_off_deg": None,
             "ran_prelude": []}]
    table = script.table(rows)
    assert "| open_drawer | 1 / 1 | 0 / 1 | 1 |" in table and "| rotate_block_left | 0 / 0 | 0 / 0 | - |" in table


def test_one_run_has_its_prelude_done_first_and_notes_the_yaw(script):
    """The script's episode with the oracle in the policy's place: the drawer prelude, then the press."""
    from trivla_drake.tasks.oracle import OraclePolicy

    row = script.run(script._YawAtStart(OraclePolicy()), OraclePolicy(), "open_drawer", "turn_on_light", 0)
    assert row["ran_prelude"] == ["open_drawer"] and row["success"], row["reason"]
    assert row["yaw_off_deg"] is not None and 0.0 <= row["yaw_off_deg"] <= 90.0
