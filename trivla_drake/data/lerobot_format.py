"""The LeRobot dataset format (v3.0) as this project writes and reads it: paths, episode columns, features.

Layout (paths as in lerobot's `CHUNK_FILE_PATTERN`; `LeRobotWriter` (lerobot_writer.py) puts one episode in each
file, which the format allows, so that every episode is committed on its own; `LeRobotReader` (lerobot_reader.py)
reads it back):

    meta/info.json                                   fps, features, path templates, totals
    meta/tasks.parquet                               task (instruction text, the index) -> task_index
    meta/stats.json                                  per-feature min / max / mean / std / count and the
                                                     quantiles q01 / q10 / q50 / q90 / q99 (lerobot_stats.py)
    meta/episodes/chunk-XXX/file-XXX.parquet         one row per episode: length, tasks, file
                                                     indices, frame range, per-episode stats
    data/chunk-XXX/file-XXX.parquet                  one row per frame: timestamp, frame_index,
                                                     episode_index, index, task_index, features
    videos/<camera key>/chunk-XXX/file-XXX.mp4       one video per camera and episode, all in one codec
                                                     (info.json's video.codec; data/video.py)

    meta/checksums.json                              sha256 of every data and video file (data/checksums.py;
                                                     not LeRobot's, which ignores it)
"""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
DATA_PATH = "data/" + CHUNK_FILE + ".parquet"
VIDEO_PATH = "videos/{video_key}/" + CHUNK_FILE + ".mp4"
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE + ".parquet"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
# Episode-metadata column naming the suite task an episode demonstrates (`collect` writes it; LeRobot's
# own task is the instruction, and one task has many phrasings).
EPISODE_TASK_KEY = "trivla/task"
# Episode-metadata columns of demonstrations collected with action noise (`collect`'s perturbation "dart"):
# the setting, and the frames whose applied action was disturbed (missing: none was).
ACTION_NOISE_KEY = "trivla/action_noise"
PERTURBED_FRAMES_KEY = "trivla/perturbed_frames"
PRELUDE_KEY = "trivla/prelude"  # tasks the oracle completed, unrecorded, before the episode's (`collect`'s prelude_tasks)
# The Arrow types of the trivla/* episode columns, so every episode's row has the same schema whatever it holds (an
# empty list would otherwise be list<null> in one file and list<string> in the next, and readers of the whole
# meta/episodes folder, pyarrow.dataset or Hugging Face datasets, drop or refuse such columns).
EPISODE_COLUMN_TYPES = {
    EPISODE_TASK_KEY: pa.string(),
    "trivla/attempt": pa.int64(),
    "trivla/seed": pa.int64(),
    "trivla/params": pa.list_(pa.string()),
    ACTION_NOISE_KEY: pa.float64(),
    PERTURBED_FRAMES_KEY: pa.list_(pa.int64()),
    PRELUDE_KEY: pa.list_(pa.string()),
}
# What a `collect` episode without one of these settings records (before session 66 it left the column out).
EPISODE_COLUMN_DEFAULTS = {ACTION_NOISE_KEY: 0.0, PERTURBED_FRAMES_KEY: [], PRELUDE_KEY: []}
# Columns of collection experiments that left the product (code at git tag `research-archive`), at the value every
# episode the product can still collect had in them: datasets written before still read (the columns are ignored),
# and `with_removed_columns` puts them back where a row lacks them, so an episode's keys stay what they were.
REMOVED_EPISODE_COLUMNS = {
    "trivla/yaw_twists": False, "trivla/missed_grasps": False, "trivla/approach_drifts": False,
    "trivla/takeover": "", "trivla/stacked_pick": False, "trivla/detours": 0,
}


def with_removed_columns(row: dict) -> dict:
    """`row` as the collector before the removal wrote it: a row with every EPISODE_COLUMN_DEFAULTS column (written
    since session 66, when every column went into every row) gets the REMOVED_EPISODE_COLUMNS it lacks at their
    values; an older row, which left unused columns out, stays as it is."""
    if not all(key in row for key in EPISODE_COLUMN_DEFAULTS):
        return row
    return {**REMOVED_EPISODE_COLUMNS, **row}


TASKS_PATH = "meta/tasks.parquet"
DEFAULT_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}


class NotADatasetError(ValueError):
    """A folder that is not a LeRobot dataset (or not one this code can read)."""


def episode_files(row: dict, data_path: str, video_path: str | None, video_keys: list[str]) -> list[str]:
    """The data and video files (paths relative to the dataset folder) holding one episode's frames."""
    try:
        files = [data_path.format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])]
        for key in video_keys:
            files.append(video_path.format(video_key=key, chunk_index=row[f"videos/{key}/chunk_index"],
                                           file_index=row[f"videos/{key}/file_index"]))
    except KeyError as error:
        raise NotADatasetError(f"the meta/episodes row of episode {row.get('episode_index')} has no column {error} "
                               "that meta/info.json's features call for: an edited or damaged dataset") from error
    return files


def read_episode_rows(root: Path) -> list[dict]:
    """The committed episodes' meta/episodes rows, in episode order."""
    rows = []
    for path in sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet")):
        rows.extend(pq.read_table(path).to_pylist())
    rows.sort(key=lambda r: r["episode_index"])
    return rows


def info_fps(fps: float) -> int:
    """`fps` as info.json stores it (lerobot v3 reads an integer); ValueError for a rate that is no whole number."""
    if not float(fps).is_integer() or fps <= 0:
        raise ValueError(f"fps must be a positive whole number of frames per second (LeRobot v3 stores an integer "
                         f"fps), got {fps}")
    return int(fps)


def video_feature(height: int, width: int, fps: float, codec: str = "mpeg4") -> dict:
    """The info.json entry of a camera stored as mp4 (`LeRobotWriter` sets codec and pix_fmt from the files)."""
    return {
        "dtype": "video",
        "shape": [height, width, 3],
        "names": ["height", "width", "channels"],
        "info": {
            "video.height": height,
            "video.width": width,
            "video.codec": codec,
            "video.pix_fmt": "yuv420p",
            "video.is_depth_map": False,
            "video.fps": info_fps(fps),
            "video.channels": 3,
            "has_audio": False,
        },
    }


def dataset_video_codec(root: str | Path) -> str | None:
    """The codec of the videos of the dataset at `root` (info.json's video.codec; a dataset written before the
    codec was a choice has 'mpeg4'); None where `root` holds no committed episode with videos (nothing fixes it)."""
    path = Path(root) / INFO_PATH
    try:
        info = json.loads(path.read_text())
        videos = [f for f in info["features"].values() if f.get("dtype") == "video"]
        if not videos or not info.get("total_episodes"):
            return None
        return videos[0].get("info", {}).get("video.codec", "mpeg4")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None  # no dataset there (or not one this reads): the writer says what is wrong with it


def vector_feature(names: list[str], dtype: str = "float32") -> dict:
    """The info.json entry of a per-frame vector."""
    return {"dtype": dtype, "shape": [len(names)], "names": list(names)}
