"""`evaluate --out`'s journal (eval/evaluation_journal.py): a killed evaluation resumes with the report an unbroken
run gives, a larger one reuses a smaller one's results, and a journal of other settings is refused, never
overwritten."""

from __future__ import annotations

import json

import pytest

from trivla_drake.eval import evaluate as evaluate_module
from trivla_drake.eval.evaluate import EvalConfig, evaluate
from trivla_drake.eval.evaluation_journal import JOURNAL_FILE, journal_key, policy_fingerprint


def _config(out, **changes) -> EvalConfig:
    settings = dict(policy="random", tasks=["turn_on_light", "open_drawer"], episodes=2, chains=1, max_steps=6,
                    out=str(out))
    return EvalConfig(**{**settings, **changes})


@pytest.fixture
def job_calls(monkeypatch):
    """The jobs run (not taken from a journal), in order."""
    calls = []
    run_job = evaluate_module._run_job

    def counted(config, job):
        calls.append(job)
        return run_job(config, job)

    monkeypatch.setattr(evaluate_module, "_run_job", counted)
    return calls


def _without_config(report: dict) -> dict:
    return {key: value for key, value in report.items() if key != "config"}


def test_a_killed_evaluation_resumes_and_reports_what_an_unbroken_run_does(tmp_path, job_calls):
    whole = evaluate(_config(tmp_path / "whole"), progress=False)
    assert len(job_calls) == 5  # 2 tasks x 2 episodes, 1 chain
    journal = (tmp_path / "whole" / JOURNAL_FILE).read_bytes()
    lines = journal.splitlines(keepends=True)
    assert len(lines) == 6 and json.loads(lines[0])["key"]["policy"] == "random"
    # Killed after two results, halfway through writing the third.
    (tmp_path / "killed").mkdir()
    (tmp_path / "killed" / JOURNAL_FILE).write_bytes(b"".join(lines[:3]) + lines[3][: len(lines[3]) // 2])
    job_calls.clear()
    resumed = evaluate(_config(tmp_path / "killed"), progress=False)
    assert job_calls == [("episode", "turn_on_light", 1, 1000), ("episode", "open_drawer", 1, 1000),
                         ("chain", "chain", 0, 1000)]
    assert _without_config(resumed) == _without_config(whole)
    assert (tmp_path / "killed" / JOURNAL_FILE).read_bytes() == journal
    job_calls.clear()
    assert _without_config(evaluate(_config(tmp_path / "killed"), progress=False)) == _without_config(whole)
    assert job_calls == []  # everything stored: nothing runs


def test_more_chains_or_another_seed_run_only_what_is_missing(tmp_path, job_calls):
    evaluate(_config(tmp_path, episodes=0, tasks=[], chains=1), progress=False)
    job_calls.clear()
    report = evaluate(_config(tmp_path, episodes=0, tasks=[], chains=2, seeds=[1000, 1001]), progress=False)
    assert job_calls == [("chain", "chain", 1, 1000), ("chain", "chain", 0, 1001), ("chain", "chain", 1, 1001)]
    assert len(report["per_seed"]) == 2


def test_a_journal_of_other_settings_is_refused_and_kept(tmp_path, job_calls):
    evaluate(_config(tmp_path, episodes=1, chains=0), progress=False)
    journal = (tmp_path / JOURNAL_FILE).read_bytes()
    with pytest.raises(ValueError, match=r"other settings \(max_steps: 6 there, 7 now; paraphrases: the default there, "
                                         r"True now\); it is kept"):
        evaluate(_config(tmp_path, episodes=1, chains=0, paraphrases=True, max_steps=7), progress=False)
    assert (tmp_path / JOURNAL_FILE).read_bytes() == journal
    for notes in ("my notes\n", "my notes without a newline"):
        (tmp_path / JOURNAL_FILE).write_text(notes)
        with pytest.raises(ValueError, match="is not an evaluation journal.*it is kept"):
            evaluate(_config(tmp_path, episodes=1, chains=0), progress=False)
        assert (tmp_path / JOURNAL_FILE).read_text() == notes


def test_the_key_holds_what_decides_a_result_and_fields_only_off_their_defaults(tmp_path):
    key = journal_key(_config(tmp_path))
    assert key["policy"] == "random" and key["max_steps"] == 6 and key["threads"] == 1
    assert "paraphrases" not in key and "hold_check" not in key  # at their defaults
    assert not {"tasks", "episodes", "chains", "seed", "seeds", "workers", "out"} & set(key)
    # A serial run's threads decide its numbers; Ray workers run 1 each, whatever `threads` says.
    assert journal_key(_config(tmp_path, threads=2))["threads"] == 2
    assert journal_key(_config(tmp_path, threads=2, workers=2)) == key


def test_a_stored_job_whose_video_is_asked_for_and_missing_runs_again(tmp_path, job_calls):
    config = _config(tmp_path, tasks=["turn_on_light"], episodes=2, chains=0, image_size=32)
    first = evaluate(config, progress=False)
    job_calls.clear()
    config.record_dir = str(tmp_path / "videos")
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "turn_on_light-000.mp4").write_bytes(b"kept")  # there already
    again = evaluate(config, progress=False)
    assert job_calls == [("episode", "turn_on_light", 1, 1000)]
    assert (tmp_path / "videos" / "turn_on_light-001.mp4").stat().st_size > 0
    assert _without_config(again) == _without_config(first)


def test_a_complete_journal_reports_without_starting_ray(tmp_path, job_calls, monkeypatch):
    from trivla_drake.eval import rollout_runner

    evaluate(_config(tmp_path, episodes=1, chains=0), progress=False)
    job_calls.clear()

    def no_runner(*args, **kwargs):
        raise AssertionError("a runner was started with nothing to run")

    monkeypatch.setattr(rollout_runner, "RolloutRunner", no_runner)
    report = evaluate(_config(tmp_path, episodes=1, chains=0, workers=2), progress=False)
    assert job_calls == [] and set(report["tasks"]) == {"turn_on_light", "open_drawer"}


def test_a_checkpoint_is_known_by_its_contents_not_its_folder(tmp_path):
    import torch

    from trivla_drake.nn import TriVLA, make_config, save_checkpoint

    model = TriVLA(make_config("tiny"))
    save_checkpoint(model, str(tmp_path / "ckpt"))
    first = policy_fingerprint(str(tmp_path / "ckpt"))
    assert first.startswith("checkpoint sha256 ") and policy_fingerprint(str(tmp_path / "ckpt")) == first
    with torch.no_grad():
        next(model.parameters()).add_(1.0)
    save_checkpoint(model, str(tmp_path / "ckpt"))  # retrained into the same folder
    assert policy_fingerprint(str(tmp_path / "ckpt")) != first
    assert policy_fingerprint("oracle") == "oracle"
