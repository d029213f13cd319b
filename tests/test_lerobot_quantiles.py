"""The quantile statistics lerobot v3 records (q01 / q10 / q50 / q90 / q99), per episode and for the dataset, and
datasets written before them: still read, resumed without them (one schema per dataset)."""

import json
import logging

import numpy as np
import pyarrow.parquet as pq
import pytest

from trivla_drake.data.lerobot_format import vector_feature, video_feature
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_stats import (
    BASE_METRICS,
    QUANTILES,
    aggregate_stats,
    array_stats,
    image_stats,
    without_quantiles,
)
from trivla_drake.data.lerobot_writer import LeRobotWriter

FPS = 36.0
CAMERA = "observation.images.static"
FEATURES = {CAMERA: video_feature(16, 16, FPS), "observation.state": vector_feature(["s0", "s1"])}


def _episode(length: int, offset: float):
    state = np.stack([np.arange(length, dtype=np.float32) + offset, np.full(length, offset, np.float32)], axis=1)
    frames = np.zeros((length, 16, 16, 3), np.uint8)
    frames[:, :8] = 200  # the top half bright, the bottom dark, in every channel
    return {"observation.state": state}, {CAMERA: frames}


def test_episode_quantiles_are_order_statistics():
    """Of the values 1..100, quantile q is the value 100 q (the smallest with a fraction q at or below it)."""
    values = np.arange(1, 101, dtype=float)[:, None] * [1.0, -2.0]
    stats = array_stats(values)
    for key, q in QUANTILES.items():
        assert stats[key][0] == pytest.approx(100 * q)
        assert stats[key][1] == pytest.approx(-2 * (101 - 100 * q))  # the second column, reversed and scaled
    # What existed before the quantiles is unchanged, in its order.
    assert array_stats(values, quantiles=False) == without_quantiles(stats)
    assert list(array_stats(values, quantiles=False)) == BASE_METRICS


def test_image_quantiles_are_per_channel_and_shaped_3_1_1():
    frames = np.zeros((10, 8, 8, 3), np.uint8)
    frames[:, :4, :, 0] = 255  # channel 0: half the pixels white; channel 1: all 51; channel 2: black
    frames[..., 1] = 51
    stats = image_stats(frames, frame_stride=1, pixel_stride=1)
    for key in QUANTILES:
        assert np.shape(stats[key]) == (3, 1, 1)
    channels = {key: np.asarray(stats[key])[:, 0, 0].tolist() for key in QUANTILES}
    assert channels["q01"] == [0.0, 0.2, 0.0] and channels["q50"] == [0.0, 0.2, 0.0]
    assert channels["q90"] == [1.0, 0.2, 0.0] and channels["q99"] == [1.0, 0.2, 0.0]
    assert stats["count"] == [10]


def test_dataset_quantiles_are_the_count_weighted_mean_and_need_every_part():
    one = array_stats(np.array([[0.0]]))  # count 1, every quantile 0
    three = array_stats(np.array([[4.0], [4.0], [4.0]]))  # count 3, every quantile 4
    merged = aggregate_stats([{"x": one}, {"x": three}])["x"]
    assert merged["q50"] == [3.0] and merged["q01"] == [3.0] and merged["count"] == [4]
    mixed = aggregate_stats([{"x": without_quantiles(one)}, {"x": three}])["x"]
    assert not set(QUANTILES) & set(mixed)  # a part written before the quantiles: none in the aggregate
    assert mixed["mean"] == merged["mean"] and mixed["std"] == merged["std"]


def test_written_dataset_records_quantiles_per_episode_and_in_stats_json(tmp_path):
    root = tmp_path / "ds"
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES)
    for length, offset in ((5, 0.0), (15, 100.0)):
        frames, videos = _episode(length, offset)
        writer.add_episode(frames, "task", videos=videos)
    reader = LeRobotReader(root)
    first, second = reader.episodes
    assert first["stats/observation.state/q50"] == [2.0, 0.0]
    assert second["stats/observation.state/q50"] == [107.0, 100.0]
    assert np.shape(first[f"stats/{CAMERA}/q99"]) == (3, 1, 1)
    for feature in ("observation.state", CAMERA, "timestamp", "frame_index", "episode_index", "index", "task_index"):
        assert set(reader.stats[feature]) == set(BASE_METRICS) | set(QUANTILES), feature
    np.testing.assert_allclose(reader.stats["observation.state"]["q50"], (5 * np.array([2.0, 0.0]) + 15 * np.array(
        [107.0, 100.0])) / 20)
    np.testing.assert_allclose(np.asarray(reader.stats[CAMERA]["q90"])[:, 0, 0], 200 / 255)


def test_a_dataset_written_before_the_quantiles_is_resumed_without_them(tmp_path, caplog):
    root = tmp_path / "old"
    old = LeRobotWriter(root, fps=FPS, features=FEATURES)
    old.records_quantiles = False  # as the writer before the quantiles wrote its episodes
    frames, videos = _episode(5, 0.0)
    old.add_episode(frames, "task", videos=videos)
    before = (root / "meta/stats.json").read_text()
    assert '"q50"' not in before
    with caplog.at_level(logging.WARNING):
        resumed = LeRobotWriter(root, fps=FPS, features=FEATURES)
    assert not resumed.records_quantiles and "written before quantile statistics" in caplog.text
    frames, videos = _episode(7, 10.0)
    stats = image_stats(videos[CAMERA])  # what `collect` hands over, quantiles and all: they are dropped
    resumed.add_episode(frames, "task", videos=videos, video_stats={CAMERA: stats})
    schemas = [pq.read_schema(p) for p in sorted((root / "meta/episodes").glob("*/*.parquet"))]
    assert len(schemas) == 2 and schemas[0].names == schemas[1].names  # one schema, as lerobot's readers need
    assert not [name for name in schemas[1].names if name.rsplit("/", 1)[-1] in QUANTILES]
    stats_json = json.loads((root / "meta/stats.json").read_text())
    assert set(stats_json["observation.state"]) == set(BASE_METRICS)
    assert LeRobotReader(root).stats["observation.state"]["count"] == [12]


def test_video_stats_without_quantiles_are_refused_by_a_new_dataset(tmp_path):
    writer = LeRobotWriter(tmp_path / "ds", fps=FPS, features=FEATURES)
    frames, videos = _episode(5, 0.0)
    bare = image_stats(videos[CAMERA], quantiles=False)
    with pytest.raises(ValueError, match=r"video_stats\['observation.images.static'\] has no quantiles"):
        writer.add_episode(frames, "task", videos=videos, video_stats={CAMERA: bare})
    assert writer.num_episodes == 0
