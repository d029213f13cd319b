"""The grasp report: where the gripper first closes against the named block, measured on real closed-loop
episodes; the oracle closes on the block and succeeds, a grounded model gets its sub-goals recorded,
and bad settings are refused naming the field."""

import dataclasses
import json

import numpy as np
import pytest

from trivla_drake.eval.grasp_report import (
    GraspRow,
    _SubgoalRecorder,
    format_grasp_report,
    grasp_report,
    grasp_summary,
)
from trivla_drake.nn.config import make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.tasks.oracle import OraclePolicy


def test_the_oracle_closes_on_the_named_block_and_lifts_it():
    rows = grasp_report(OraclePolicy(), episodes_per_task=1, tasks=("lift_block",))
    (row,) = rows
    assert row.success and row.close_step is not None and row.close_step > 0
    assert row.closes == 1  # one grasp, held
    assert row.nearest_block_named and row.close_to_block_m < 0.015
    assert 0.01 < row.close_height_m < 0.05
    assert abs(row.close_yaw_error_deg) < 5.0  # the expert turns the hand to the block's faces
    assert row.first_subgoal_to_block_m is None and row.close_to_subgoal_m is None  # no grounding
    summary = grasp_summary(rows)
    assert (summary["episodes"], summary["successes"], summary["closed_within_1_5_cm"]) == (1, 1, 1)
    assert (summary["closed_again"], summary["successes_after_closing_again"]) == (0, 0)
    assert summary["closed_within_15_deg"] == 1 and summary["median_abs_close_yaw_error_deg"] < 5.0
    text = format_grasp_report(rows)
    assert "| lift_block | 1000 | yes |" in text and "1/1 succeed" in text and "(again after opening in 0" in text
    assert "the hand's yaw within 15 degrees of the block's faces in 1" in text


def test_a_grounded_model_gets_its_subgoal_recorded_per_chunk(tmp_path, capsys):
    from trivla_drake.cli import main
    from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy
    from trivla_drake.nn.checkpoint import save_checkpoint

    config = make_config("tiny")
    model = TriVLA(dataclasses.replace(config, policy=dataclasses.replace(config.policy, instruction_grounding=True)))
    policy = TriVLAHarnessPolicy(model.eval())
    (row,) = grasp_report(policy, episodes_per_task=1, tasks=("stack_block",), max_steps=30)
    assert row.first_subgoal_to_block_m is not None and 0 <= row.first_subgoal_to_block_m < 2.0
    assert (row.close_step is None) == (row.close_to_subgoal_m is None)
    # chunks are looked up by the step they start at
    recorder = _SubgoalRecorder(policy, grounded=True)
    recorder.reset("lift the red block", 0)
    recorder.chunks.extend([(0, np.zeros(3)), (10, np.ones(3))])
    assert recorder.subgoal_at(0)[0] == 0 and recorder.subgoal_at(9)[0] == 0 and recorder.subgoal_at(10)[0] == 1
    save_checkpoint(model, tmp_path / "grounded")
    assert main(["probe", "--checkpoint", str(tmp_path / "grounded"), "--grasp-episodes", "-1"]) == 2
    assert "--grasp-episodes must be at least 0 and at most 100000" in capsys.readouterr().err


def test_bad_settings_are_refused_naming_the_field():
    with pytest.raises(ValueError, match="episodes_per_task must be >= 1"):
        grasp_report(OraclePolicy(), episodes_per_task=0)
    with pytest.raises(ValueError, match="tasks must be among lift_block"):
        grasp_report(OraclePolicy(), tasks=("open_drawer",))


def test_summary_of_episodes_that_never_close():
    row = GraspRow("lift_block", 1000, "lift the red block", False, first_subgoal_to_block_m=0.04)
    summary = grasp_summary([row])
    assert summary["closed"] == 0 and summary["median_close_to_block_cm"] is None
    assert summary["median_first_subgoal_to_block_cm"] == 4.0
    assert "| never |" in format_grasp_report([row])
    json.dumps(summary)


def test_closes_count_every_close_from_open():
    from trivla_drake.eval.grasp_report import count_closes

    assert count_closes(np.array([1.0, 1.0, 1.0])) == 0
    assert count_closes(np.array([-1.0, -1.0, 1.0])) == 1  # closed from the start
    assert count_closes(np.array([1.0, -1.0, -1.0, 1.0, 1.0, -0.5, 1.0, 0.0])) == 3
