"""The LeRobot-format writer and reader, training samples, and resumable collection."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from trivla_drake.data import lerobot_writer
from trivla_drake.data.lerobot_format import NotADatasetError, vector_feature, video_feature
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.data.samples import TrainingSamples

FPS = 36.0
FEATURES = {
    "observation.images.static": video_feature(16, 16, FPS),
    "observation.state": vector_feature([f"s{i}" for i in range(3)]),
    "action": vector_feature([f"a{i}" for i in range(7)]),
}


def _episode(length: int, seed: int):
    rng = np.random.default_rng(seed)
    frames = {
        "observation.state": rng.normal(size=(length, 3)).astype(np.float32),
        "action": rng.uniform(-1, 1, size=(length, 7)).astype(np.float32),
    }
    # Flat-coloured frames whose brightness encodes the frame index (survives lossy compression).
    video = np.zeros((length, 16, 16, 3), np.uint8)
    video[:] = (np.arange(length) * 8 % 256).astype(np.uint8)[:, None, None, None]
    return frames, video


def _write(root, lengths, tasks):
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES)
    episodes = []
    for i, (length, task) in enumerate(zip(lengths, tasks)):
        frames, video = _episode(length, i)
        writer.add_episode(frames, task, videos={"observation.images.static": video}, extra={"trivla/seed": i})
        episodes.append((frames, video))
    return writer, episodes


def test_written_dataset_reads_back(tmp_path):
    root = tmp_path / "ds"
    _, episodes = _write(root, [5, 7, 4], ["lift the red block", "open the drawer", "lift the red block"])
    reader = LeRobotReader(root)
    assert reader.num_episodes == 3 and reader.num_frames == 16
    assert reader.tasks == ["lift the red block", "open the drawer"]
    info = json.loads((root / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["total_frames"] == 16 and info["fps"] == FPS
    assert info["features"]["timestamp"]["dtype"] == "float32"
    for i, (frames, video) in enumerate(episodes):
        got = reader.episode_frames(i)
        np.testing.assert_array_equal(got["action"], frames["action"])
        np.testing.assert_array_equal(got["episode_index"], i)
        np.testing.assert_allclose(got["timestamp"], np.arange(len(video)) / FPS, rtol=1e-6)
        decoded = reader.episode_video(i, "observation.images.static")
        assert decoded.shape == video.shape
        assert np.abs(decoded.astype(int) - video.astype(int)).mean() < 3
    assert reader.episode_frames(2)["task_index"].tolist() == [0] * 4
    assert reader.episode_frames(1)["index"].tolist() == list(range(5, 12))
    # Stats over all frames equal the direct computation.
    actions = np.concatenate([f["action"] for f, _ in episodes])
    np.testing.assert_allclose(reader.stats["action"]["mean"], actions.mean(0), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(reader.stats["action"]["std"], actions.std(0), rtol=1e-5)
    np.testing.assert_allclose(reader.stats["action"]["min"], actions.min(0))
    assert reader.stats["action"]["count"] == [16]
    assert np.shape(reader.stats["observation.images.static"]["mean"]) == (3, 1, 1)
    # tasks.parquet carries the task text as its pandas index, as lerobot reads it.
    meta = json.loads(pq.read_schema(root / "meta/tasks.parquet").metadata[b"pandas"])
    assert meta["index_columns"] == ["task"]
    assert reader.episodes[1]["trivla/seed"] == 1


def test_not_a_dataset_is_a_clear_error(tmp_path):
    with pytest.raises(NotADatasetError, match="meta/info.json is missing"):
        LeRobotReader(tmp_path)
    with pytest.raises(NotADatasetError, match="no such directory"):
        LeRobotReader(tmp_path / "nope")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(NotADatasetError, match="not a LeRobot dataset"):
        LeRobotWriter(tmp_path, fps=FPS, features=FEATURES)
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta/info.json").write_text("{not json")
    with pytest.raises(NotADatasetError, match="unreadable"):
        LeRobotReader(tmp_path)
    # The writer (collect resuming into --out) names the file too, whatever is wrong with it.
    for text in ("{not json", '{"codebase_version": "v3.0"}', "[]"):
        (tmp_path / "meta/info.json").write_text(text)
        with pytest.raises(NotADatasetError, match="meta/info.json is not a readable LeRobot info file"):
            LeRobotWriter(tmp_path, fps=FPS, features=FEATURES)
    (tmp_path / "a_file").write_text("not a folder")
    with pytest.raises(NotADatasetError, match="a_file is a file, not a dataset folder"):
        LeRobotWriter(tmp_path / "a_file", fps=FPS, features=FEATURES)


def test_a_crash_before_the_commit_loses_only_that_episode(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    _write(root, [5, 6], ["a", "b"])
    real = lerobot_writer._atomic_write_table

    def crash_on_commit(path, table):
        if "meta/episodes" in str(path):
            raise KeyboardInterrupt("killed while committing")
        real(path, table)

    writer = LeRobotWriter(root, fps=FPS, features=FEATURES)
    monkeypatch.setattr(lerobot_writer, "_atomic_write_table", crash_on_commit)
    frames, video = _episode(9, 7)
    with pytest.raises(KeyboardInterrupt):
        writer.add_episode(frames, "new task", videos={"observation.images.static": video})
    monkeypatch.setattr(lerobot_writer, "_atomic_write_table", real)
    reader = LeRobotReader(root)
    assert reader.num_episodes == 2 and reader.num_frames == 11
    assert reader.episode_frames(1)["action"].shape == (6, 7)
    # Reopening resumes: the next episode (another one, shorter) takes index 2 and overwrites the orphaned files.
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES)
    assert writer.num_episodes == 2
    frames, video = _episode(5, 11)
    writer.add_episode(frames, "new task", videos={"observation.images.static": video})
    reader = LeRobotReader(root)
    assert reader.num_episodes == 3 and reader.num_frames == 16
    np.testing.assert_array_equal(reader.episode_frames(2)["action"], frames["action"])
    assert len(reader.episode_video(2, "observation.images.static")) == 5
    assert json.loads((root / "meta/info.json").read_text())["total_episodes"] == 3
    with pytest.raises(ValueError, match="fps"):
        LeRobotWriter(root, fps=10.0, features=FEATURES)


def test_training_samples_history_future_and_chunks(tmp_path):
    root = tmp_path / "ds"
    _, episodes = _write(root, [12, 5], ["a", "b"])
    samples = TrainingSamples(root, history=3, future_frames=4, future_stride=2, chunk_size=10)
    assert len(samples) == 17
    first = samples[0]
    frames, video = episodes[0]
    assert first["observation.state"].shape == (3, 3)
    assert first["observation_is_pad"].tolist() == [True, True, False]
    np.testing.assert_array_equal(first["observation.state"][0], frames["observation.state"][0])
    np.testing.assert_array_equal(first["action"], frames["action"][:10])
    assert not first["action_is_pad"].any()
    brightness = lambda clip: np.round(clip.reshape(len(clip), -1).mean(1) / 8).astype(int).tolist()  # noqa: E731
    assert brightness(first["future.images.static"]) == [2, 4, 6, 8]
    last = samples[11]  # the last frame of episode 0
    assert last["action_is_pad"].tolist() == [False] + [True] * 9
    np.testing.assert_array_equal(last["action"][1:, :6], 0.0)  # padding holds still ...
    np.testing.assert_array_equal(last["action"][1:, 6], frames["action"][-1, 6])  # ... with the last gripper
    assert last["future_is_pad"].all() and brightness(last["future.images.static"]) == [11] * 4
    second = samples[12]
    assert second["episode_index"] == 1 and second["frame_index"] == 0 and second["instruction"] == "b"
    with pytest.raises(IndexError):
        samples[17]


def _collect_command(out: Path, episodes: int) -> list[str]:
    return [sys.executable, "-m", "trivla_drake.eval.cli_commands", "collect", "--out", str(out),
            "--episodes-per-task", str(episodes), "--tasks", "turn_on_light", "--set", "image_size=32",
            "--no-progress", "--json"]


def test_killed_collection_keeps_finished_episodes_and_resumes(tmp_path):
    out = tmp_path / "demos"
    process = subprocess.Popen(_collect_command(out, 4), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    committed = out / "meta" / "episodes" / "chunk-000"
    deadline = time.time() + 120
    while time.time() < deadline and len(list(committed.glob("file-*.parquet"))) < 1:
        time.sleep(0.05)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    reader = LeRobotReader(out)
    killed_at = reader.num_episodes
    assert 1 <= killed_at < 4
    for i in range(killed_at):
        assert reader.episode_frames(i)["action"].shape[1] == 7
        assert len(reader.episode_video(i, "observation.images.wrist")) == reader.episodes[i]["length"]
    # The same command again finishes the job without redoing what was committed.
    finished = subprocess.run(_collect_command(out, 4), capture_output=True, text=True, timeout=300)
    assert finished.returncode == 0, finished.stderr
    summary = json.loads(finished.stdout)
    assert summary["per_task"] == {"turn_on_light": 4}
    reader = LeRobotReader(out)
    assert reader.num_episodes == 4
    attempts = [e["trivla/attempt"] for e in reader.episodes]
    assert len(set(attempts)) == 4
    samples = TrainingSamples(reader)
    assert samples[len(samples) - 1]["action"].shape == (10, 7)
    assert not (out / ".staging").exists()
    # The dataset keeps the config that made it, which `collect --config` reads back.
    from trivla_drake.config_io import load_config
    from trivla_drake.eval.collect import CONFIG_FILE, CollectConfig

    stored = load_config(CollectConfig, out / CONFIG_FILE)
    assert stored == CollectConfig(out=str(out), episodes_per_task=4, tasks=["turn_on_light"], image_size=32)


def test_collected_episode_rows_share_one_schema(tmp_path):
    """Every episode's meta/episodes row has every trivla/* column in one type (an unused setting at its default), so
    the folder reads as one table; before, a fixture task's empty params were list<null> beside list<string>."""
    import pyarrow.dataset as ds

    from trivla_drake.data.lerobot_format import EPISODE_COLUMN_DEFAULTS, EPISODE_COLUMN_TYPES
    from trivla_drake.eval.collect import CollectConfig, collect

    out = tmp_path / "mixed"
    collect(CollectConfig(out=str(out), episodes_per_task=1, tasks=["lift_block", "open_drawer"], image_size=32),
            progress=False)
    table = ds.dataset(out / "meta" / "episodes", format="parquet").to_table()
    assert table.num_rows == 2
    for name, kind in EPISODE_COLUMN_TYPES.items():
        assert table.schema.field(name).type == kind, name
    rows = table.to_pylist()
    params = {r["trivla/task"]: r["trivla/params"] for r in rows}
    assert params["open_drawer"] == [] and len(params["lift_block"]) == 1 and isinstance(params["lift_block"][0], str)
    # Unused settings are written as EPISODE_COLUMN_DEFAULTS, which content keys leave out (dataset_union).
    for key, default in EPISODE_COLUMN_DEFAULTS.items():
        assert all(r[key] == default for r in rows), key
    # The columns of removed collection experiments are no longer written.
    from trivla_drake.data.lerobot_format import REMOVED_EPISODE_COLUMNS

    assert not set(REMOVED_EPISODE_COLUMNS) & set(table.schema.names)


def test_rows_without_the_removed_experiment_columns_keep_their_episode_keys():
    """A row written now (no removed-experiment columns) hashes as the same collection written before the removal
    (every column, the removed ones at their off values); a row from before session 66 (unused columns left out)
    stays as it was; the union's content keys match old and new rows."""
    from types import SimpleNamespace

    from trivla_drake.data.lerobot_format import EPISODE_COLUMN_DEFAULTS, REMOVED_EPISODE_COLUMNS, with_removed_columns
    from trivla_drake.train.dataset_union import episode_row_key
    from trivla_drake.train.datasets import episode_fingerprint

    new = {"episode_index": 0, "length": 40, "trivla/task": "lift_block", **EPISODE_COLUMN_DEFAULTS}
    before_removal = {**new, **REMOVED_EPISODE_COLUMNS}
    older = {"episode_index": 0, "length": 40, "trivla/task": "lift_block"}
    assert with_removed_columns(new) == before_removal and with_removed_columns(older) == older

    def reader(row):
        return SimpleNamespace(episodes=[row], features={}, camera_keys=[])

    assert episode_fingerprint(reader(new), 0) == episode_fingerprint(reader(before_removal), 0)
    assert episode_fingerprint(reader(older), 0) != episode_fingerprint(reader(new), 0)
    assert episode_row_key(reader(new), 0) == episode_row_key(reader(before_removal), 0) == episode_row_key(
        reader(older), 0)
    turned_on = {**before_removal, "trivla/detours": 2}  # an experiment's episode stays another episode
    assert episode_row_key(reader(turned_on), 0) != episode_row_key(reader(new), 0)
