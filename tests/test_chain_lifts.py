"""results/chain_lifts: the lifts it reruns are the stored chains' (their count and outcomes are the docstring's),
the recorder traces what the policy plans without changing it, and the summary classifies each lift's outcome."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture
def lifts(results_script):
    return results_script("chain_lifts/chain_lifts.py")


@pytest.fixture
def summary(results_script):
    return results_script("chain_lifts/summarise.py")


def test_every_lift_of_the_stored_chains_is_found_with_its_outcome(lifts):
    jobs = lifts.stored_chain_tasks("lift_block")
    assert len(jobs) == 32 and sum(ok for *_, ok in jobs) == 13  # the docstring's figures
    third = [ok for _, _, position, ok in jobs if position == 3]
    assert len(third) == 10 and sum(third) == 2
    assert (1003, 0, 3, False) in jobs  # place_in_bowl, rotate_block_left, then the lift that failed
    stacks = lifts.stored_chain_tasks("stack_block")
    assert len(stacks) == 26 and sum(ok for *_, ok in stacks) == 6  # chain_positions.md: 20 of 26 failed


def _scene():
    from trivla_drake.tasks.scene import Layout, sample_scene, scene_from_spec

    layout = Layout.default()
    return scene_from_spec(sample_scene(np.random.default_rng(3), layout), layout)


class _Env:
    def __init__(self):
        self.step_index, self._scene = 40, _scene()

    def scene(self):
        return self._scene


class _Policy:
    name, uses_images, privileged = "fake", True, False

    def __init__(self):
        self.calls = []

    def reset(self, instruction, seed):
        self.calls.append(("reset", instruction, seed))

    def act(self, observation):
        self.calls.append(("act", observation["time"]))
        return np.tile([0.0] * 6 + [-1.0 if observation["time"] > 1.0 else 1.0], (10, 1))


def test_the_recorder_passes_everything_through_and_traces_the_named_block(lifts):
    env, policy = _Env(), _Policy()
    recorder = lifts.ChunkRecorder(policy, env)
    recorder.reset("stack the green block on the red block", 7)
    assert policy.calls == [("reset", "stack the green block on the red block", 7)]
    assert recorder.tasks[0]["color"] == "green" and recorder.tasks[0]["start"]["base"] is None
    tcp = np.eye(4)
    block = env.scene().block_position("green")
    tcp[:3, 3] = block + [0.03, 0.04, 0.05]
    for step, time in ((52, 0.5), (62, 1.5), (72, 2.0)):
        env.step_index = step
        rows = recorder.act({"time": time, "tcp_pose": tcp, "state": np.zeros(18)})
        assert rows.shape == (10, 7)
    trace = lifts.grasp_trace(recorder.tasks[0])
    assert trace["homing_steps"] == 12  # the first chunk the policy planned, 12 steps into the task
    assert trace["first_close"]["step"] == 22 and trace["first_close"]["xy_to_block_cm"] == pytest.approx(5.0)
    assert trace["closes"] == 1 and trace["chunks_closed"] == 2 and not trace["ever_held"]


def test_success_within_the_budget_and_the_extended_one_come_from_one_run(lifts):
    assert lifts.outcome(True, 360, 360, 108) == {"success": True, "success_extended": True, "steps": 360,
                                                  "budget": 360, "budget_extended": 468}
    assert lifts.outcome(True, 361, 360, 108)["success"] is False
    assert lifts.outcome(False, 468, 360, 108)["success_extended"] is False


def test_a_negative_extra_budget_is_refused_naming_the_flag(lifts, capsys):
    with pytest.raises(SystemExit):
        lifts.main(["trivla", "out.json", "--budget-extra", "-5"])
    assert "--budget-extra must be >= 0" in capsys.readouterr().err


def _row(position, success=False, extended=False, close=None, held=False):
    return {"task": "lift_block", "budget": 360, "seed": 1003, "chain": 1, "position": position, "before": [["open_drawer", True, 170]] * (position - 1),
            "reached": True, "success": success, "success_extended": extended, "steps": 300, "homing_steps": 60,
            "first_close": close, "closes": int(close is not None), "ever_held": held, "max_block_z_cm": 2.3,
            "start": {"base": None, "block": [0.5, 0.0, 0.0225], "nearest_other_m": 0.2, "drawer_opening": 0.0, "yaw_to_hand_deg": 5.0}}


def test_the_summary_classifies_each_outcome(summary):
    close = {"step": 100, "xy_to_block_cm": 2.0, "tcp_z_cm": 5.0}
    rows = [_row(0, True, True, close, True), _row(2, False, True, close, True), _row(3), _row(3, close=close),
            _row(3, close=close, held=True)]
    modes = [summary.failure_mode(r) for r in rows]
    assert modes == ["succeeded", "succeeded after its budget", "never closed the gripper",
                     "closed, never held the block", "held the block, not lifted 10 cm"]
    text = summary.summarise({"task": "lift_block", "budget_extra": 108,
                              "chain_tasks": rows[1:] + [{**_row(4), "reached": False}], "single_tasks": rows[:1]})
    assert "lift_block in chains, rerun: 5, of which 4 reached" in text
    assert "| on the table | 5 | 1 | +2.8 (+2.8 to +2.8) |" in text  # 5.0 cm against the block's 2.25
    assert "| chain task 3 | 3 | 0 | 0 | 60 |" in text
    assert "| never closed the gripper | 0 | 1 |" in text


def test_where_the_block_stands_as_the_task_starts(summary):
    row = _row(2)
    assert summary.stands(row) == "on the table"
    assert summary.stands({**row, "start": {**row["start"], "base": "red"}}) == "on another block"
    assert summary.stands({**row, "start": {**row["start"], "block": [0.4, 0.0, 0.16]}}) == "in the hand"


def test_a_traced_oracle_lift_closes_on_the_block_and_lifts_it(lifts, summary):
    """In the simulator: the oracle's grasp is the reference (it closes 0.3 cm above the block's centre)."""
    row = lifts.run_single_task("oracle", 1000, 0, "lift_block", 0)
    assert row["success"] and row["ever_held"] and row["max_block_z_cm"] > 9  # as last planned: it ends at 10
    assert row["budget"] == row["budget_extended"] == 360
    assert row["first_close"]["xy_to_block_cm"] < 1.0
    assert abs(summary.close_above_centre_cm(row) - 0.3) < 1.0
    assert summary.failure_mode(row) == "succeeded" and summary.stands(row) == "on the table"


def test_the_stacked_pick_comparison_counts_the_same_seeds_in_every_row(results_script, tmp_path):
    compare = results_script("chain_lifts/stacked_compare.py")
    for policy in ("oracle", "shipped"):
        for seed in compare.SEEDS:
            tasks = {t: {"successes": 1 if policy == "oracle" else 0, "episodes": 2} for t in compare.TASKS}
            (tmp_path / f"{policy}_seed{seed}.json").write_text(json.dumps({"tasks": tasks}))
    assert compare.stacked_counts("oracle", tmp_path) == {t: (6, 12) for t in compare.TASKS}
    traces = tmp_path / "traces"
    traces.mkdir()
    for task, name in compare.TRACES.items():
        rows = [{"seed": s, "success": s % 2 == 0} for s in (*compare.SEEDS, 1006, 1017)]
        (traces / name).write_text(json.dumps({"single_tasks": rows}))
    assert compare.usual_counts(traces) == {t: (3, 6) for t in compare.TASKS}  # seeds 1006 and 1017 left out
