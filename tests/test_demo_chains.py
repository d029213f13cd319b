"""`demo --chains`: 5-task chains with TriVLA as Drake systems, the instruction input changed as each task is done."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


@pytest.fixture(scope="module")
def tiny_model():
    from trivla_drake.nn import TriVLA, make_config

    return TriVLA(make_config("tiny"), load_pretrained=False)


class _Predicate:
    """Stands in for every task's success predicate (an untrained model completes nothing)."""

    def __init__(self, monkeypatch, answer):
        import trivla_drake.eval.demo_chains as demo_chains
        from trivla_drake.tasks.suite import get_task

        self.answer = answer

        class Task:
            def __init__(self, name):
                self.real = get_task(name)
                self.max_steps = self.real.max_steps

            def success(task, params, initial, current):
                return self.answer(params, initial, current)

        monkeypatch.setattr(demo_chains, "get_task", Task)


def test_a_chain_hands_each_task_to_the_policy_in_turn(tiny_model, monkeypatch):
    from trivla_drake.eval.demo import CHECK_PERIOD_S
    from trivla_drake.eval.demo_chains import run_trivla_chain_demo

    # Each task is "done" at the first check after it starts (the predicate sees a new scene read).
    _Predicate(monkeypatch, lambda params, initial, current: initial is not current)
    handed = []

    def on_task_start(chain, k, instance, context):
        handed.append((chain, k, instance, context.get_time(), context))

    import trivla_drake.eval.demo_chains as demo_chains

    built = []
    real_build = demo_chains.build_demo_loop
    monkeypatch.setattr(demo_chains, "build_demo_loop", lambda *a, **k: built.append(real_build(*a, **k)) or built[-1])

    def check_instruction(chain, k, instance, context):
        on_task_start(chain, k, instance, context)
        seen = built[0].loop.diagram.GetInputPort("instruction").Eval(context)
        assert seen == instance.instruction

    report = run_trivla_chain_demo(tiny_model, chains=1, seed=1003, on_task_start=check_instruction).as_dict()
    assert [k for _, k, *_ in handed] == [0, 1, 2, 3, 4]
    assert len({h[2].task for h in handed}) == 5  # a chain prefers tasks it has not used
    starts = [h[3] for h in handed]
    assert starts == pytest.approx([k * CHECK_PERIOD_S for k in range(5)])  # one simulation, task after task
    assert report["chain_avg_len"] == 5.0 and report["chains"]["completed_at_least"] == [1.0] * 5
    run = report["chain_runs"][0]
    assert run["completed"] == 5 and run["reason"] == ""
    assert [s["task"] for s in run["subtasks"]] == [h[2].task for h in handed]
    assert report["sim_time"] == pytest.approx(5 * CHECK_PERIOD_S)
    assert report["control_hz"] > 0


def test_a_chain_ends_at_its_first_failure(tiny_model, monkeypatch):
    from trivla_drake.eval.demo_chains import run_trivla_chain_demo

    _Predicate(monkeypatch, lambda params, initial, current: False)
    report = run_trivla_chain_demo(tiny_model, chains=2, seed=1003, max_seconds=0.5).as_dict()
    assert report["chain_avg_len"] == 0.0 and report["chains"]["count"] == 2
    for run in report["chain_runs"]:
        assert run["completed"] == 0 and len(run["subtasks"]) == 1
        assert run["reason"] == f"{run['subtasks'][0]['task']}: timeout"
        assert run["subtasks"][0]["sim_time"] == pytest.approx(0.5)
    assert report["chains"]["by_position"][0] == {"position": 1, "tried": 2, "succeeded": 0,
                                                  "failed_tasks": sorted(r["subtasks"][0]["task"]
                                                                         for r in report["chain_runs"])}


def test_a_task_already_done_when_drawn_is_not_counted(tiny_model, monkeypatch):
    from trivla_drake.eval.demo_chains import run_trivla_chain_demo

    _Predicate(monkeypatch, lambda params, initial, current: True)
    run = run_trivla_chain_demo(tiny_model, chains=1, seed=1003).as_dict()["chain_runs"][0]
    assert run["completed"] == 0 and run["reason"].endswith("predicate already true at the start "
                                                            "(not counted as a success)")


def test_chain_j_starts_as_the_harness_chain_j(tiny_model):
    """The same scene and first task (with its instruction) as `evaluate --chains`'s chain of that index."""
    from trivla_drake.eval.demo_chains import run_trivla_chain_demo
    from trivla_drake.eval.episode import derive_seed, run_chain
    from trivla_drake.eval.policies import RandomPolicy

    report = run_trivla_chain_demo(tiny_model, chains=2, seed=1003, max_seconds=0.3).as_dict()
    for j, run in enumerate(report["chain_runs"]):
        harness = run_chain(derive_seed(1003, "chain", j), RandomPolicy(), max_steps=1)
        assert run["seed"] == harness.seed
        assert (run["subtasks"][0]["task"], run["subtasks"][0]["instruction"]) == (
            harness.subtasks[0].task, harness.subtasks[0].instruction)


def test_chain_demo_refuses_bad_settings(tiny_model):
    from trivla_drake.eval.demo_chains import run_trivla_chain_demo

    for kwargs, field in (({"chains": 0}, "chains"), ({"chains": 1, "length": 6}, "length"),
                          ({"chains": 1, "execute_steps": 11}, "execute_steps")):
        with pytest.raises(ValueError, match=field):
            run_trivla_chain_demo(tiny_model, **kwargs)


def _cli(*args, timeout=600):
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
    return subprocess.run([sys.executable, "-m", "trivla_drake.cli", "demo", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_cli_runs_chains_and_prints_avg_len(tmp_path, tiny_model):
    from trivla_drake.nn import save_checkpoint

    save_checkpoint(tiny_model, str(tmp_path / "tiny"))
    result = _cli("--checkpoint", str(tmp_path / "tiny"), "--chains", "1", "--set", "max_seconds=0.5")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "| chains | 1/5 | 2/5 | 3/5 | 4/5 | 5/5 | Avg. Len |" in result.stdout
    assert "| 0.00 (one chain) |" in result.stdout  # no standard error from a single chain
    assert "Avg. Len 0.00, control" in result.stdout and "| 0 (1/5) |" in result.stdout
    assert "demo chains" in result.stderr  # the progress bar
    shown = _cli("--checkpoint", str(tmp_path / "tiny"), "--chains", "1", "--set", "max_seconds=0.3", "--json",
                 "--no-progress")
    report = json.loads(shown.stdout)
    assert report["chain_avg_len"] == 0.0 and len(report["chain_runs"]) == 1 and "success_rate" not in report


@pytest.mark.parametrize("args, message", [
    (["--chains", "0"], "--chains must be at least 1"),
    (["--chains", "2", "--task", "lift_block"], "leave out --task"),
    (["--chains", "2", "--episodes", "3"], "leave out --episodes"),
    (["--chains", "2", "--policy", "oracle"], "evaluate --policy oracle --episodes 0 --chains N"),
    (["--episodes", "0"], "--episodes must be at least 1"),
])
def test_cli_refuses_chains_with_other_settings(args, message, capsys):
    from trivla_drake.cli import main

    assert main(["demo", *args]) == 2  # before any model is loaded or simulation built
    assert message in capsys.readouterr().err
