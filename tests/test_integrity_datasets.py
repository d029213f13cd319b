"""Datasets record the sha256 of every data and video file (meta/checksums.json, atomically with each episode's
commit); training and feature caching check them, and the feature cache is keyed by them."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest

from trivla_drake.data.checksums import CHECKSUMS_PATH, DatasetCorruptError, file_sha256
from trivla_drake.data.checksums import main as record_checksums
from trivla_drake.data.lerobot_format import vector_feature, video_feature
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.train.synthetic import write_synthetic_dataset

STATIC = "observation.images.static"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("integrity") / "data", episodes=2, length=8, image_size=16)


def _copy(dataset, tmp_path):
    return str(shutil.copytree(dataset, tmp_path / "data"))


def _flip_bytes(path, at=0.5, count=8):
    data = bytearray(path.read_bytes())
    start = int(len(data) * at)
    for i in range(start, start + count):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def test_every_data_and_video_file_is_recorded(dataset):
    reader = LeRobotReader(dataset)
    files = [f for e in range(reader.num_episodes) for f in reader.episode_files(e)]
    assert len(files) == 2 * 3 and any(f.startswith("data/") for f in files) and any(f.endswith(".mp4") for f in files)
    recorded = json.loads((reader.root / CHECKSUMS_PATH).read_text())
    assert recorded["algorithm"] == "sha256"
    assert recorded["files"] == {f: file_sha256(reader.root / f) for f in files}
    reader.verify_files()  # intact


def test_flipped_bytes_in_a_data_file_stop_training_naming_the_file(dataset, tmp_path):
    from trivla_drake.train import TrainConfig, train

    root = _copy(dataset, tmp_path)
    data_file = LeRobotReader(root).episode_files(1)[0]
    _flip_bytes(tmp_path / "data" / data_file)
    with pytest.raises(DatasetCorruptError, match=rf"{data_file}.*corrupted or was changed.*restore it"):
        LeRobotReader(root).verify_files()
    config = TrainConfig(stage="policy", out=str(tmp_path / "run"), data=root, preset="tiny", steps=1, batch_size=2,
                         cache_dir=str(tmp_path / "cache"), progress=False)
    with pytest.raises(DatasetCorruptError, match=data_file):
        train(config)
    assert not (tmp_path / "cache").exists()  # refused before any feature was cached


def test_a_replaced_video_is_refused_then_gets_new_features_once_recorded(dataset, tmp_path):
    import torch

    from trivla_drake.nn.presets import make_config
    from trivla_drake.nn.trivla import TriVLA
    from trivla_drake.train import TrainConfig
    from trivla_drake.train.distributed import DistEnv
    from trivla_drake.train.features import ensure_feature_cache

    root = _copy(dataset, tmp_path)
    model = TriVLA(make_config("tiny")).eval()
    config = TrainConfig(stage="policy", out=str(tmp_path / "run"), data=root, preset="tiny",
                         cache_dir=str(tmp_path / "cache"), progress=False).resolved()
    before, _ = ensure_feature_cache(model, LeRobotReader(root), [0, 1], config, DistEnv(), progress=False)
    reader = LeRobotReader(root)
    video0, video1 = (reader.episode_files(e)[1] for e in (0, 1))
    assert STATIC in video0
    shutil.copyfile(tmp_path / "data" / video1, tmp_path / "data" / video0)  # another episode's video
    with pytest.raises(DatasetCorruptError, match=video0):
        ensure_feature_cache(model, LeRobotReader(root), [0, 1], config, DistEnv(), progress=False)
    assert record_checksums([root]) == 0  # replaced on purpose: recorded as it is now
    after, summary = ensure_feature_cache(model, LeRobotReader(root), [0, 1], config, DistEnv(), progress=False)
    assert after[0] != before[0] and after[1] == before[1]
    assert summary["feature_shards_computed"] == 1 and summary["feature_shards_reused"] == 1
    from safetensors.torch import load_file

    assert not torch.equal(load_file(str(after[0]))["q_vl"], load_file(str(before[0]))["q_vl"])


def test_a_dataset_without_checksums_loads_with_one_warning_and_can_record_them(dataset, tmp_path, caplog):
    root = _copy(dataset, tmp_path)
    (tmp_path / "data" / CHECKSUMS_PATH).unlink()  # as written before checksums were recorded
    reader = LeRobotReader(root)
    with caplog.at_level(logging.WARNING):
        reader.verify_files()
    warnings = [r for r in caplog.records if "records no checksums" in r.getMessage()]
    assert len(warnings) == 1 and "python -m trivla_drake.data.checksums" in warnings[0].getMessage()
    digests = reader.episode_digests(0)
    record_checksums([root])
    fresh = LeRobotReader(root)
    assert fresh.checksums is not None and fresh.episode_digests(0) == digests


def test_a_crash_before_the_commit_keeps_the_checksums_of_committed_episodes_only(tmp_path, monkeypatch):
    import trivla_drake.data.lerobot_writer as lerobot_writer

    features = {"observation.state": vector_feature(["a", "b"]), "action": vector_feature(["x"]),
                STATIC: video_feature(8, 8, 10.0)}

    def episode(seed):
        rng = np.random.default_rng(seed)
        return ({"observation.state": rng.normal(size=(4, 2)), "action": rng.normal(size=(4, 1))},
                {STATIC: rng.integers(0, 255, size=(4, 8, 8, 3), dtype=np.uint8)})

    root = tmp_path / "ds"
    writer = LeRobotWriter(root, fps=10.0, features=features)
    frames, videos = episode(0)
    writer.add_episode(frames, "task", videos=videos)
    real = lerobot_writer._atomic_write_table

    def crash_on_commit(path, table):
        if "meta/episodes" in str(path):
            raise KeyboardInterrupt("killed")
        real(path, table)

    monkeypatch.setattr(lerobot_writer, "_atomic_write_table", crash_on_commit)
    frames, videos = episode(1)
    with pytest.raises(KeyboardInterrupt):
        writer.add_episode(frames, "task", videos=videos)
    monkeypatch.setattr(lerobot_writer, "_atomic_write_table", real)
    reader = LeRobotReader(root)
    assert reader.num_episodes == 1
    assert sorted(reader.checksums) != sorted(reader.episode_files(0))  # the uncommitted episode's files too
    resumed = LeRobotWriter(root, fps=10.0, features=features)  # what collect --resume does
    assert sorted(LeRobotReader(root).checksums) == sorted(reader.episode_files(0))
    frames, videos = episode(2)
    resumed.add_episode(frames, "task", videos=videos)
    final = LeRobotReader(root)
    assert final.num_episodes == 2
    final.verify_files()  # the rewritten episode's files carry their new checksums
    assert sorted(final.checksums) == sorted(f for e in range(2) for f in final.episode_files(e))
