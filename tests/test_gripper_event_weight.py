"""`train --gripper-event-weight W`: the frames just before each gripper change (the last approach to a
grasp or a release) are sampled W times as often, reproducibly and resumably; bad values are named."""

from __future__ import annotations

import collections
import json

import numpy as np
import pytest

from trivla_drake.data.lerobot import LeRobotReader
from trivla_drake.data.subgoals import before_gripper_event_frames
from trivla_drake.train import TrainConfig, train
from trivla_drake.train.sampler import StepBatchSampler
from trivla_drake.train.synthetic import write_synthetic_dataset


def test_the_frames_before_each_gripper_change():
    gripper = np.array([1, 1, 1, 1, 1, -1, -1, -1, -1, 1, 1], dtype=float)  # closes at 5, opens at 9
    near = before_gripper_event_frames(gripper, window=3)
    assert np.flatnonzero(near).tolist() == [3, 4, 5, 7, 8, 9]
    assert not before_gripper_event_frames(np.ones(6), window=3).any()  # no change, no event
    with pytest.raises(ValueError, match="gripper must be"):
        before_gripper_event_frames(np.ones((3, 2)), window=3)


def test_repeated_samples_come_as_often_as_their_weight_and_batches_stay_a_function_of_the_step():
    repeats = np.ones(20, dtype=int)
    repeats[[3, 11]] = 4
    sampler = StepBatchSampler(20, 2, seed=5, total_steps=1000, repeats=repeats)
    assert sampler.steps_per_epoch == (18 + 8) // 2
    epoch = [i for s in range(sampler.steps_per_epoch) for i in sampler.batch_at(s)]
    counts = collections.Counter(epoch)
    assert counts[3] == counts[11] == 4 and all(counts[i] == 1 for i in range(20) if i not in (3, 11))
    resumed = StepBatchSampler(20, 2, seed=5, start_step=37, total_steps=1000, repeats=repeats)
    assert list(resumed)[:5] == [sampler.batch_at(s) for s in range(37, 42)]
    uniform = StepBatchSampler(20, 2, seed=5, total_steps=1000)
    assert [uniform.batch_at(s) for s in range(10)] != [sampler.batch_at(s) for s in range(10)]


@pytest.mark.parametrize("repeats, match", [(np.ones(5), "one integer >= 1 per sample"),
                                            (np.zeros(6), "one integer >= 1 per sample")])
def test_bad_repeats_are_refused(repeats, match):
    with pytest.raises(ValueError, match=match):
        StepBatchSampler(6, 2, seed=0, total_steps=3, repeats=repeats)


@pytest.mark.parametrize("changes, match", [
    (dict(gripper_event_weight=0), "gripper_event_weight"),
    (dict(gripper_event_weight=2.5), "gripper_event_weight"),
    (dict(gripper_event_window_s=0.0), "gripper_event_window_s"),
    (dict(stage="video", gripper_event_weight=3), "policy stage only"),
    (dict(gripper_event_weight=3, gripper_event_window_s=float("inf")), "gripper_event_window_s"),
    (dict(gripper_event_window_s=0.5), "needs --gripper-event-weight above 1"),
])
def test_bad_settings_are_named(changes, match):
    config = TrainConfig(**{"stage": "policy", "out": "o", "data": "d", **changes}).resolved()
    with pytest.raises(ValueError, match=match):
        config.validate()


def test_a_cli_run_with_a_bad_weight_fails_before_any_work(tmp_path, capsys):
    from trivla_drake.cli import main

    assert main(["train", "--stage", "policy", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "run"),
                 "--gripper-event-weight", "0"]) == 2
    assert "--gripper-event-weight" in capsys.readouterr().err
    assert main(["train", "--stage", "policy", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "run"),
                 "--gripper-event-weight", "3", "--gripper-event-window", "-1"]) == 2
    assert "--gripper-event-window" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_a_policy_run_weights_the_frames_before_gripper_changes(tmp_path, monkeypatch):
    import trivla_drake.train.sampler as sampler_module

    data = write_synthetic_dataset(tmp_path / "data", episodes=3, length=24)
    reader = LeRobotReader(data)
    window = 9  # 0.25 s at 36 fps
    assert reader.fps == 36.0
    expected = 0
    for episode in range(3):  # the cached frames (stride 2) within 9 frames before a change
        gripper = np.asarray(reader.episode_frames(episode)["action"])[:, 6]
        expected += int(before_gripper_event_frames(gripper, window)[::2].sum())
    given = []

    class RecordingSampler(StepBatchSampler):
        def __init__(self, *args, repeats=None, **kwargs):
            given.append(None if repeats is None else np.asarray(repeats))
            super().__init__(*args, repeats=repeats, **kwargs)

    monkeypatch.setattr(sampler_module, "StepBatchSampler", RecordingSampler)
    summary = train(TrainConfig(stage="policy", data=data, out=str(tmp_path / "run"), preset="tiny", steps=3,
                                batch_size=4, cache_dir=str(tmp_path / "cache"), progress=False, feature_stride=2,
                                use_system2=False, use_system3=False, gripper_event_weight=3,
                                gripper_event_window_s=0.25))
    assert 0 < expected < summary["samples"]
    assert summary["gripper_event_samples"] == expected
    assert given[0].max() == 3 and int((given[0] == 3).sum()) == expected  # the sampler got the weights
    saved = json.loads((tmp_path / "run" / "final" / "train_config.json").read_text())
    assert (saved["gripper_event_weight"], saved["gripper_event_window_s"]) == (3, 0.25)
