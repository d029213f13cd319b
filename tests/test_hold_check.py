"""`evaluate --set hold_check=SECONDS`: each success is asked again after the hand is held still that long."""

from __future__ import annotations

import json

import pytest

from trivla_drake.eval import episode as episode_module
from trivla_drake.eval.cli_commands import main
from trivla_drake.eval.episode import derive_seed, run_chain, run_episode, shared_env
from trivla_drake.eval.evaluate import EvalConfig, evaluate, format_markdown, summarize
from trivla_drake.eval.policies import RandomPolicy
from trivla_drake.tasks.oracle import OraclePolicy


class _ScriptedPredicate:
    """Stands in for every task's predicate: false at a task's start, true after its first step, then (the check
    after the hold) the next answer of `after_hold`. Counts the control steps between the two checks."""

    def __init__(self, monkeypatch, after_hold: list[bool]):
        self.after_hold = list(after_hold)
        self.steps_between: list[int] = []
        predicate = self
        real_get_task = episode_module.get_task

        class Task:
            def __init__(self, name):
                self.real = real_get_task(name)

            def __getattr__(self, name):  # everything but the predicate is the real task's
                return getattr(self.real, name)

            def success(task, params, initial, current):
                env = shared_env(None)
                if current is initial:  # the check at the task's start
                    predicate.succeeded_at = None
                    return False
                if predicate.succeeded_at is None:
                    predicate.succeeded_at = env.step_index
                    return True
                predicate.steps_between.append(env.step_index - predicate.succeeded_at)
                return predicate.after_hold.pop(0)

        monkeypatch.setattr(episode_module, "get_task", lambda name: Task(name))


def test_a_success_that_does_not_last_is_reported_as_such(monkeypatch):
    predicate = _ScriptedPredicate(monkeypatch, [False, True])
    first = run_episode("turn_on_light", 7, RandomPolicy(), hold_check=0.5)
    second = run_episode("turn_on_light", 8, RandomPolicy(), hold_check=0.5)
    assert first.success and first.lasted is False and first.steps == 1
    assert second.success and second.lasted is True
    assert predicate.steps_between == [18, 18]  # 0.5 s at the 36 Hz control rate
    assert first.to_dict()["lasted"] is False
    # Without a hold check nothing is held and nothing asked again; the stored reports' keys are unchanged.
    plain = run_episode("turn_on_light", 9, RandomPolicy())
    assert plain.success and plain.lasted is None and "lasted" not in plain.to_dict()
    assert predicate.after_hold == []


def test_a_chain_counts_the_successes_in_a_row_that_lasted(monkeypatch):
    # Five tasks done as the predicates first hold; the second one's success does not last.
    predicate = _ScriptedPredicate(monkeypatch, [True, False, True, True, True])
    chain = run_chain(derive_seed(1000, "chain", 0), RandomPolicy(), hold_check=0.25)
    assert chain.completed == 5 and chain.completed_lasting == 1, chain.reason
    assert predicate.steps_between == [9] * 5
    assert [s.lasted for s in chain.subtasks] == [True, False, True, True, True]
    assert chain.to_dict()["completed_lasting"] == 1
    assert "completed_lasting" not in run_chain(derive_seed(1000, "chain", 0), RandomPolicy(), max_steps=1).to_dict()


def test_the_oracle_s_stack_and_lift_last():
    """Physics: the hold keeps the gripper's last command, so a lifted block stays up and a stacked one stays on."""
    report = evaluate(EvalConfig(policy="oracle", tasks=["lift_block", "stack_block"], episodes=1, hold_check=0.5),
                      progress=False)
    for row in report["tasks"].values():
        assert row["successes"] == row["lasting_successes"] == 1 and row["lasting_rate"] == 1.0
    assert report["average_lasting_success"] == 1.0


def test_the_report_and_its_table():
    config = EvalConfig(policy="oracle", tasks=["stack_block"], episodes=4, chains=2, hold_check=0.5)
    episodes = [{"task": "stack_block", "seed": i, "instruction": "stack", "reason": "", "success": ok, "lasted": lasted}
                for i, (ok, lasted) in enumerate([(True, True), (True, False), (True, True), (False, None)])]
    episodes[3]["reason"] = "timeout"
    chains = [{"seed": 1, "completed": 3, "completed_lasting": 1, "reason": "x: timeout", "subtasks": []},
              {"seed": 2, "completed": 2, "completed_lasting": 2, "reason": "y: timeout", "subtasks": []}]
    report = summarize(config, episodes, chains)
    row = report["tasks"]["stack_block"]
    assert (row["successes"], row["lasting_successes"], row["lasting_rate"]) == (3, 2, 0.5)
    assert row["lasting_stderr"] == pytest.approx(0.25)
    assert report["average_lasting_success"] == 0.5
    assert report["chain_avg_len"] == 2.5 and report["chain_avg_len_lasting"] == 1.5
    assert report["chain_avg_len_lasting_stderr"] == pytest.approx(0.5)
    assert report["chains"]["completed_lasting"] == [1, 2] and report["chains"]["completed"] == [3, 2]
    table = format_markdown(json.loads(json.dumps(report)))
    assert "| task | success | std. error | still a success after 0.5 s held | std. error | episodes |" in table
    assert "| stack_block | 0.750 | 0.217 | 0.500 | 0.250 | 4 |" in table
    assert "after the hand was held still 0.5 s: 1.50 ± 0.50" in table
    # Without a hold check: the table and report as before.
    plain = summarize(EvalConfig(policy="oracle", tasks=["stack_block"], episodes=4), episodes, [])
    assert "lasting_successes" not in plain["tasks"]["stack_block"] and "average_lasting_success" not in plain
    assert "held" not in format_markdown(plain)


@pytest.mark.parametrize("value", ["0", "-1", ".nan", ".inf", "11"])
def test_a_bad_hold_check_is_refused_naming_the_field(value, capsys):
    assert main(["evaluate", "--tasks", "lift_block", "--episodes", "1", "--set", f"hold_check={value}",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "hold_check must be" in err and "seconds" in err
    with pytest.raises(ValueError, match="hold_check"):
        run_episode("lift_block", 1, OraclePolicy(), hold_check=float(value.lstrip(".")))


def test_evaluate_cli_prints_the_lasting_column(capsys):
    assert main(["evaluate", "--tasks", "turn_on_light", "--episodes", "1", "--set", "hold_check=0.2",
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "still a success after 0.2 s held" in out and "| turn_on_light | 1.000 | 0.000 | 1.000 | 0.000 | 1 |" in out


def test_a_simulation_failure_in_the_hold_keeps_the_success(monkeypatch):
    """The success was counted when the predicate first held; a simulation failing during the hold makes it one that
    did not last, and ends a chain after counting it."""
    _ScriptedPredicate(monkeypatch, [True] * 10)
    real_step = episode_module.TabletopEnv.step
    policy_steps = {"left": 1}

    def step(env, action, *, images=True):
        if policy_steps["left"] == 0:  # every step after the policy's first is the hold's
            raise episode_module.SimulationError("injected in the hold")
        policy_steps["left"] -= 1
        return real_step(env, action, images=images)

    monkeypatch.setattr(episode_module.TabletopEnv, "step", step)
    result = run_episode("turn_on_light", 3, RandomPolicy(), hold_check=0.5)
    assert result.success and result.lasted is False and result.reason == "hold check: injected in the hold"
    policy_steps["left"] = 1
    chain = run_chain(derive_seed(1000, "chain", 0), RandomPolicy(), hold_check=0.5)
    assert (chain.completed, chain.completed_lasting, len(chain.subtasks)) == (1, 0, 1)
    assert chain.reason.endswith("hold check: injected in the hold")


def test_the_hold_adds_video_frames_and_no_trajectory_rows(monkeypatch):
    frames = {}

    def finish(recorder):  # keeps the frames instead of writing the video
        frames[len(frames)] = list(recorder.frames or [])

    monkeypatch.setattr(episode_module._Recorder, "finish", finish)
    _ScriptedPredicate(monkeypatch, [True])
    held = run_episode("turn_on_light", 5, RandomPolicy(), hold_check=0.25, keep_trajectory=True, video_path="unused.mp4")
    plain = run_episode("turn_on_light", 5, RandomPolicy(), keep_trajectory=True, video_path="unused.mp4")
    assert held.steps == plain.steps == 1
    assert len(held.trajectory) == len(plain.trajectory) == 1  # the policy's one step, the hold's none
    assert len(frames[1]) == 2 and len(frames[0]) == 2 + 9  # before and after the step; the hold's 9 steps between
    assert (frames[0][0] == frames[1][0]).all()
