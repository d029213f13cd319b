"""What the LeRobot writer records about frame numbering and images, read back against what was written.

Nothing read `frame_index` or the image statistics' channels back, so numbering frames from 1 or pooling
the statistics over the three colours went unnoticed. The frames here hold a different constant in each
channel, so per-channel statistics are known exactly: value / 255, standard deviation 0.
"""

import numpy as np
import pytest

from trivla_drake.data.lerobot_format import vector_feature, video_feature
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_writer import LeRobotWriter

FPS = 36.0
CAMERA = "observation.images.static"
FEATURES = {CAMERA: video_feature(16, 16, FPS), "observation.state": vector_feature(["s0", "s1"])}
# Episode length and the (R, G, B) value of every pixel of its frames.
EPISODES = [(7, (40, 130, 220)), (4, (200, 10, 90))]


@pytest.fixture(scope="module")
def reader(tmp_path_factory):
    root = tmp_path_factory.mktemp("mutation_lerobot") / "ds"
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES)
    for i, (length, rgb) in enumerate(EPISODES):
        video = np.empty((length, 16, 16, 3), np.uint8)
        video[:] = np.asarray(rgb, np.uint8)
        state = np.arange(2 * length, dtype=np.float32).reshape(length, 2) + 100 * i
        writer.add_episode({"observation.state": state}, "lift the red block", videos={CAMERA: video})
    return LeRobotReader(root)


def _channels(value):
    """A (3, 1, 1) image statistic as a (3,) array."""
    array = np.asarray(value, dtype=float)
    assert array.shape == (3, 1, 1), array.shape
    return array[:, 0, 0]


def test_frame_index_counts_from_zero_in_every_episode(reader):
    for i, (length, _) in enumerate(EPISODES):
        frames = reader.episode_frames(i)
        np.testing.assert_array_equal(frames["frame_index"], np.arange(length))
        row = reader.episodes[i]
        assert row["stats/frame_index/min"] == [0] and row["stats/frame_index/max"] == [length - 1]
    assert reader.stats["frame_index"]["min"] == [0]
    assert reader.stats["frame_index"]["max"] == [max(length for length, _ in EPISODES) - 1]


def test_image_statistics_are_per_colour_channel(reader):
    for i, (_, rgb) in enumerate(EPISODES):
        row = reader.episodes[i]
        expected = np.asarray(rgb) / 255.0
        for metric in ("mean", "min", "max"):
            np.testing.assert_allclose(_channels(row[f"stats/{CAMERA}/{metric}"]), expected, rtol=0, atol=1e-12,
                                       err_msg=f"episode {i} image {metric}")
        np.testing.assert_allclose(_channels(row[f"stats/{CAMERA}/std"]), 0.0, atol=1e-12)
    # The dataset's statistics: per-channel extremes over the episodes, the count-weighted mean.
    colours = np.array([rgb for _, rgb in EPISODES]) / 255.0
    counts = np.array([reader.episodes[i][f"stats/{CAMERA}/count"][0] for i in range(len(EPISODES))], float)
    stats = reader.stats[CAMERA]
    np.testing.assert_allclose(_channels(stats["min"]), colours.min(0), atol=1e-12)
    np.testing.assert_allclose(_channels(stats["max"]), colours.max(0), atol=1e-12)
    np.testing.assert_allclose(_channels(stats["mean"]), counts @ colours / counts.sum(), atol=1e-12)
