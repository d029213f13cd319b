"""Mistakes a newcomer makes on the command line: exit code 2 and one line naming the flag, before any model is
loaded or simulation built (`main` in-process; no traceback)."""

from __future__ import annotations

import json

import pytest

from trivla_drake.cli import main


def _error(capsys, *argv) -> str:
    assert main(list(argv)) == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["sim", "--seconds", "0"], "--seconds must be a finite number of seconds above 0"),
    (["bench", "--preset", "tiny", "--checkpoint", "models/trivla_cpu"], "--preset (an UNTRAINED model"),
    (["demo", "--preset", "tiny", "--checkpoint", "models/trivla_cpu"], "--preset (an UNTRAINED model"),
    (["demo", "--policy", "oracle", "--preset", "tiny"], "--preset, inference.*"),
    (["demo", "--policy", "oracle", "--latency", "measured"], "--latency go with --policy trivla"),
    (["demo", "--latency", "-0.1"], "a finite number of seconds >= 0, got '-0.1'"),
    (["demo", "--latency", "soon"], "--latency must be 'zero', 'measured'"),
    (["evaluate", "--episodes", "-2"], "--episodes must be at least 0"),
    (["evaluate", "--seed", "-1"], "--seed must be an integer from 0"),
])
def test_flag_errors_name_the_flag(capsys, argv, message):
    assert message in _error(capsys, *argv)


def test_train_errors_name_the_flag(capsys, tmp_path):
    err = _error(capsys, "train", "--stage", "policy", "--data", str(tmp_path), "--out", str(tmp_path / "o"),
                 "--steps", "-5")
    assert "steps must be >= 1" in err


def test_a_checkpoint_that_is_not_one_says_what_it_is(capsys, tmp_path):
    assert "does not exist" in _error(capsys, "demo", "--checkpoint", str(tmp_path / "nope"))
    (tmp_path / "model.safetensors").write_bytes(b"")
    err = _error(capsys, "demo", "--checkpoint", str(tmp_path / "model.safetensors"))
    assert "is a file: give the folder holding config.json" in err
    dataset = tmp_path / "dataset"
    (dataset / "meta").mkdir(parents=True)
    (dataset / "meta" / "info.json").write_text(json.dumps({"fps": 36}))
    assert "is a LeRobot dataset, not a checkpoint" in _error(capsys, "demo", "--checkpoint", str(dataset))
    run = tmp_path / "run"
    (run / "final").mkdir(parents=True)
    assert "is a training run's folder: give its checkpoint" in _error(capsys, "demo", "--checkpoint", str(run))


def test_tables_name_the_checkpoint_flag(capsys, tmp_path):
    err = _error(capsys, "tables", "--full", str(tmp_path / "nope"), "--out", str(tmp_path / "t"))
    assert f"--full {tmp_path / 'nope'} is not a checkpoint directory" in err


def test_a_rollout_that_fails_on_its_workers_is_one_error_line_saying_what_is_kept(capsys, monkeypatch):
    from trivla_drake.eval import cli_commands
    from trivla_drake.eval.rollout_runner import RolloutError, WorkerDiedError

    def dies(args):
        raise WorkerDiedError("chain 17 (seed 1000): its worker died 3 times (out of memory?)")

    monkeypatch.setattr(cli_commands, "run_evaluate", dies)
    assert main(["evaluate", "--chains", "20", "--episodes", "0", "--workers", "2"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("trivla-drake evaluate: error: chain 17 (seed 1000): its worker died 3 times")
    assert "rerun the command to go on" in err and "Traceback" not in err

    def raises(args):  # the job's own error: a rerun fails the same way; --verbose gives its traceback
        raise RolloutError("chain 3 (seed 1000) failed on a worker: KeyError: 'q_vl'") from KeyError("q_vl")

    monkeypatch.setattr(cli_commands, "run_evaluate", raises)
    assert main(["evaluate", "--chains", "20", "--episodes", "0", "--workers", "2"]) == 1
    err = capsys.readouterr().err
    assert "KeyError: 'q_vl'" in err and "--verbose shows its traceback" in err and "rerun the command" not in err
    with pytest.raises(RolloutError):
        main(["-v", "evaluate", "--chains", "20", "--episodes", "0", "--workers", "2"])


@pytest.mark.parametrize("flag", ["--workers=0", "--workers=-1"])
def test_workers_below_one_are_refused_by_name(capsys, flag):
    assert "--workers must be an integer >= 1" in _error(capsys, "evaluate", "--episodes", "1", flag)


def test_a_workers_setting_of_true_is_refused_not_read_as_one():
    from trivla_drake.eval.collect_config import CollectConfig
    from trivla_drake.eval.evaluate_config import EvalConfig

    for config in (EvalConfig(workers=True), CollectConfig(out="x", workers=True)):
        with pytest.raises(ValueError, match="--workers must be an integer >= 1, got True"):
            config.validate()
