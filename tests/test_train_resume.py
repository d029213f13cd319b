"""A run killed after a checkpoint (or while writing one) and resumed ends with exactly the weights
of an uninterrupted run; checkpoints are never half-written; an existing run is never overwritten."""

from __future__ import annotations

import json

import pytest
import torch

from trivla_drake.config_io import with_flags
from trivla_drake.train import TrainConfig, train
from trivla_drake.train import checkpoints as ckpt
from trivla_drake.train.synthetic import write_synthetic_dataset




@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("resume")
    return {"data": write_synthetic_dataset(root / "data", episodes=2, length=16, image_size=16),
            "cache": str(root / "cache")}


class Killed(Exception):
    pass


# Each stage's own settings (a run of another stage refuses them).
STAGE_SETTINGS = {"video": {"video.future_stride": 2}, "vlm": {"vlm.vqa_scenes": 3, "vlm.vqa_questions_per_scene": 3},
                  "policy": {}}


def _config(stage, out, data, **kw):
    settings = {**dict(steps=6, batch_size=2, checkpoint_every=2, cache_dir=data["cache"], progress=False, lr=1e-3,
                       log_every=1), **kw}
    config = TrainConfig(stage=stage, out=str(out), data=None if stage == "vlm" else data["data"], preset="tiny",
                         **settings)
    return with_flags(config, {"optimizer.warmup_steps": 1, **STAGE_SETTINGS[stage]})


def _log(run):
    return [(entry["step"], entry["loss"]) for entry in map(json.loads, open(run / "log.jsonl"))]


def _kill_at(step):
    def callback(s):
        if s == step:
            raise Killed(f"killed after step {s}")
    return callback


@pytest.mark.parametrize("stage", ["policy", "video", "vlm"])
def test_killed_run_resumes_to_the_uninterrupted_weights(stage, data, tmp_path):
    reference = train(_config(stage, tmp_path / "ref", data))
    with pytest.raises(Killed):
        train(_config(stage, tmp_path / "run", data), step_callback=_kill_at(5))  # last checkpoint: step 4
    assert ckpt.read_step(ckpt.latest_checkpoint(tmp_path / "run")) == 4
    resumed = train(_config(stage, tmp_path / "run", data, resume=True))
    assert resumed["resumed_from_step"] == 4 and resumed["steps"] == 6
    assert resumed["weights_sha256_per_rank"] == reference["weights_sha256_per_rank"]
    ref_opt = ckpt.load_train_state(tmp_path / "ref" / "final")["optimizer"]["state"]
    run_opt = ckpt.load_train_state(tmp_path / "run" / "final")["optimizer"]["state"]
    assert all(torch.equal(ref_opt[k]["exp_avg"], run_opt[k]["exp_avg"]) for k in ref_opt)
    assert _log(tmp_path / "run") == _log(tmp_path / "ref")  # same losses, step 5 not logged twice


def test_a_kill_while_writing_a_checkpoint_leaves_the_previous_one(data, tmp_path, monkeypatch):
    reference = train(_config("policy", tmp_path / "ref", data))
    real_save = torch.save

    def dying_save(obj, path, *args, **kwargs):
        if isinstance(obj, dict) and obj.get("step") == 4:
            raise Killed("killed while writing step 4")
        return real_save(obj, path, *args, **kwargs)

    monkeypatch.setattr(ckpt.torch, "save", dying_save)
    with pytest.raises(Killed):
        train(_config("policy", tmp_path / "run", data))
    monkeypatch.setattr(ckpt.torch, "save", real_save)
    assert [step for step, _ in ckpt.list_checkpoints(tmp_path / "run")] == [2]
    assert not [p for p in (tmp_path / "run" / "checkpoints").iterdir() if p.name.startswith(".tmp")]
    resumed = train(_config("policy", tmp_path / "run", data, resume=True))
    assert resumed["resumed_from_step"] == 2
    assert resumed["weights_sha256_per_rank"] == reference["weights_sha256_per_rank"]


def test_existing_runs_need_resume_and_the_same_settings(data, tmp_path):
    train(_config("policy", tmp_path / "run", data, keep_checkpoints=1))
    assert [step for step, _ in ckpt.list_checkpoints(tmp_path / "run")] == [6]  # older ones pruned
    with pytest.raises(ValueError, match="already holds a training run"):
        train(_config("policy", tmp_path / "run", data))
    with pytest.raises(ValueError, match=r"cannot resume: lr was 0.001"):
        train(_config("policy", tmp_path / "run", data, resume=True, lr=5e-4))
    more = train(_config("policy", tmp_path / "run", data, resume=True, keep_checkpoints=1, steps=8))
    assert more["resumed_from_step"] == 6 and more["steps"] == 8
    assert ckpt.read_step(tmp_path / "run" / "final") == 8


def test_a_truncated_newest_checkpoint_resumes_from_the_newest_intact_one_and_is_kept(data, tmp_path, capsys):
    reference = train(_config("policy", tmp_path / "ref", data))
    with pytest.raises(Killed):
        train(_config("policy", tmp_path / "run", data), step_callback=_kill_at(5))  # checkpoints: steps 2, 4
    newest = tmp_path / "run" / "checkpoints" / ckpt.step_dir_name(4)
    state = newest / ckpt.STATE_FILE
    truncated = state.read_bytes()[: state.stat().st_size // 2]
    state.write_bytes(truncated)
    capsys.readouterr()
    resumed = train(_config("policy", tmp_path / "run", data, resume=True))
    assert resumed["resumed_from_step"] == 2
    assert resumed["weights_sha256_per_rank"] == reference["weights_sha256_per_rank"]
    warning = capsys.readouterr().err
    assert f"skipping checkpoint {newest}" in warning and "training_state.pt is truncated or corrupt" in warning
    kept = newest.with_name(newest.name + ".unreadable")  # never deleted, nor replaced by the resumed run's step 4
    assert (kept / ckpt.STATE_FILE).read_bytes() == truncated
    assert ckpt.read_step(ckpt.latest_checkpoint(tmp_path / "run")) == 6


def test_resume_with_no_intact_checkpoint_is_a_clear_error(data, tmp_path):
    with pytest.raises(Killed):
        train(_config("policy", tmp_path / "run", data), step_callback=_kill_at(3))  # one checkpoint: step 2
    only = tmp_path / "run" / "checkpoints" / ckpt.step_dir_name(2)
    (only / ckpt.STATE_FILE).write_bytes(b"")
    with pytest.raises(ValueError, match=rf"no checkpoint of it is intact \({only}: .*training_state.pt"):
        train(_config("policy", tmp_path / "run", data, resume=True))
    assert (only / ckpt.STATE_FILE).is_file()  # left where it was
