"""`train`'s extra_data keys repeated episodes by what they hold: the same episode at another index in another
folder is one episode, and an episode file replaced (its checksums recorded again, its metadata row left as it
was) is not mistaken for the episode it replaced."""

from __future__ import annotations

import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from trivla_drake.data import checksums
from trivla_drake.data.checksums import DatasetCorruptError
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.train.dataset_union import drop_repeated_episodes, episode_content_key
from trivla_drake.train.synthetic import CAMERAS, TASKS, synthetic_features

SIZE, FPS, LENGTH = 16, 36.0, 6


def _episode(seed: int) -> tuple[dict, dict]:
    """(columns, videos) of one small episode drawn from `seed`."""
    rng = np.random.default_rng(seed)
    columns = {"observation.state": rng.normal(size=(LENGTH, 18)).astype(np.float32),
               "action": rng.normal(size=(LENGTH, 7)).astype(np.float32)}
    videos = {camera: rng.integers(0, 256, size=(LENGTH, SIZE, SIZE, 3), dtype=np.uint8) for camera in CAMERAS}
    return columns, videos


def _write(root, seeds: list[int]) -> LeRobotReader:
    """A dataset holding the episodes of `seeds`, in that order."""
    writer = LeRobotWriter(root, fps=FPS, features=synthetic_features(SIZE, FPS))
    for seed in seeds:
        columns, videos = _episode(seed)
        writer.add_episode(columns, TASKS[0], videos=videos)
    return LeRobotReader(root)


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("union") / "first", [10, 11])


def test_the_same_episode_at_another_index_keeps_its_content_key(first, tmp_path):
    other = _write(tmp_path / "other", [11, 12])  # episode 11 at index 0 here, 1 in `first`
    assert episode_content_key(other, 0) == episode_content_key(first, 1)
    assert len({episode_content_key(first, 0), episode_content_key(first, 1), episode_content_key(other, 1)}) == 3
    assert drop_repeated_episodes([first, other], [[0, 1], [0, 1]]) == ([[0, 1], [1]], 1)


def _copy(reader: LeRobotReader, root) -> str:
    shutil.copytree(reader.root, root)
    return str(root)


def test_an_episode_whose_data_file_was_replaced_is_another_episode(first, tmp_path):
    copy = _copy(first, tmp_path / "copy")
    data_file = LeRobotReader(copy).root / LeRobotReader(copy).episode_files(1)[0]
    table = pq.read_table(data_file)
    action = table.column("action").combine_chunks()
    changed = pa.FixedSizeListArray.from_arrays(pa.array(action.flatten().to_numpy() + 0.5), action.type.list_size)
    pq.write_table(table.set_column(table.schema.get_field_index("action"), "action", changed.cast(action.type)),
                   data_file)
    assert checksums.main([copy]) == 0  # the replacement accepted on purpose; meta/episodes still as written
    replaced = LeRobotReader(copy)
    assert replaced.episodes[1] == first.episodes[1]
    assert episode_content_key(replaced, 0) == episode_content_key(first, 0)
    assert episode_content_key(replaced, 1) != episode_content_key(first, 1)
    assert drop_repeated_episodes([first, replaced], [[0, 1], [0, 1]]) == ([[0, 1], [1]], 1)


def test_an_episode_whose_video_was_replaced_is_another_episode(first, tmp_path):
    copy = _copy(first, tmp_path / "copy")
    reader = LeRobotReader(copy)
    static_0, static_1 = (reader.root / reader.episode_files(e)[1] for e in (0, 1))
    shutil.copyfile(static_0, static_1)
    assert checksums.main([copy]) == 0
    replaced = LeRobotReader(copy)
    assert episode_content_key(replaced, 1) != episode_content_key(first, 1)


def test_a_file_changed_since_its_checksum_was_recorded_is_refused_naming_it(first, tmp_path):
    copy = _copy(first, tmp_path / "copy")
    reader = LeRobotReader(copy)
    video = reader.root / reader.episode_files(1)[2]
    video.write_bytes(video.read_bytes()[:-10])
    with pytest.raises(DatasetCorruptError, match=f"dataset file {video} is corrupted or was changed"):
        drop_repeated_episodes([first, LeRobotReader(copy)], [[0, 1], [0, 1]])
