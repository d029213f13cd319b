"""Writing and reading datasets in the LeRobot format (v3.0), with pyarrow and OpenCV only.

Layout (paths as in lerobot's `CHUNK_FILE_PATTERN`; this writer puts one episode in each file, which
the format allows, so that every episode is committed on its own):

    meta/info.json                                   fps, features, path templates, totals
    meta/tasks.parquet                               task (instruction text, the index) -> task_index
    meta/stats.json                                  per-feature min / max / mean / std / count
    meta/episodes/chunk-XXX/file-XXX.parquet         one row per episode: length, tasks, file
                                                     indices, frame range, per-episode stats
    data/chunk-XXX/file-XXX.parquet                  one row per frame: timestamp, frame_index,
                                                     episode_index, index, task_index, features
    videos/<camera key>/chunk-XXX/file-XXX.mp4       one video per camera and episode

    meta/checksums.json                              sha256 of every data and video file (data/checksums.py;
                                                     not LeRobot's, which ignores it)

Atomicity: an episode's videos, data and (new) task rows are written first, each through a temporary
file renamed into place, then meta/checksums.json with their checksums added; its `meta/episodes` file
is written last and is the commit. A process killed
at any moment leaves every committed episode readable; `LeRobotWriter` reopens the folder, ignores
anything of an uncommitted episode (it is overwritten) and rebuilds info.json and stats.json from
the committed episodes' metadata.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from trivla_drake.data.checksums import RECORD_COMMAND, check_file, file_sha256, read_checksums, write_checksums
from trivla_drake.data.durable import atomic_write_bytes, fsync_file

_log = logging.getLogger(__name__)

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
# Episode-metadata columns of demonstrations collected with action noise (`collect --action-noise`):
# the setting, and the frames whose applied action was disturbed (missing: none was).
ACTION_NOISE_KEY = "trivla/action_noise"
PERTURBED_FRAMES_KEY = "trivla/perturbed_frames"
PRELUDE_KEY = "trivla/prelude"  # tasks the oracle completed, unrecorded, before the episode's (--prelude-tasks)
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


# ---------------------------------------------------------------- small file helpers
def _atomic_write_json(path: Path, data: Any) -> None:
    atomic_write_bytes(path, json.dumps(data, indent=2).encode())


def _atomic_write_table(path: Path, table: pa.Table) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(table, tmp)
    fsync_file(tmp)  # meta/episodes commits an episode: never an empty file under its name
    os.replace(tmp, path)


def _episode_files(row: dict, data_path: str, video_path: str | None, video_keys: list[str]) -> list[str]:
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


def _chunk_file(episode_index: int) -> dict[str, int]:
    return {"chunk_index": episode_index // CHUNKS_SIZE, "file_index": episode_index % CHUNKS_SIZE}


def video_feature(height: int, width: int, fps: float, codec: str = "mpeg4") -> dict:
    """The info.json entry of a camera stored as mp4."""
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
            "video.fps": fps,
            "video.channels": 3,
            "has_audio": False,
        },
    }


def vector_feature(names: list[str], dtype: str = "float32") -> dict:
    """The info.json entry of a per-frame vector."""
    return {"dtype": dtype, "shape": [len(names)], "names": list(names)}


# ---------------------------------------------------------------- statistics
def array_stats(values: np.ndarray) -> dict[str, list]:
    """min / max / mean / std / count over the first axis of (N, D) values."""
    values = np.asarray(values, dtype=np.float64)
    return {
        "min": values.min(0).tolist(),
        "max": values.max(0).tolist(),
        "mean": values.mean(0).tolist(),
        "std": values.std(0).tolist(),
        "count": [int(values.shape[0])],
    }


def image_stats(frames: np.ndarray, *, frame_stride: int = 5, pixel_stride: int = 4) -> dict[str, list]:
    """Per-channel statistics of uint8 (T, H, W, 3) frames scaled to [0, 1], shaped (3, 1, 1) as
    lerobot stores them; computed on every `frame_stride`-th frame and pixel grid point."""
    sample = np.asarray(frames)[::frame_stride, ::pixel_stride, ::pixel_stride].reshape(-1, 3) / 255.0
    stats = array_stats(sample)
    shaped = {k: [[[v]] for v in stats[k]] for k in ("min", "max", "mean", "std")}
    shaped["count"] = [int(len(frames[::frame_stride]))]
    return shaped


def aggregate_stats(per_episode: list[dict[str, dict]]) -> dict[str, dict]:
    """Combine per-episode statistics (weighted by their counts) into dataset statistics."""
    out: dict[str, dict] = {}
    keys = sorted({k for stats in per_episode for k in stats})
    for key in keys:
        parts = [s[key] for s in per_episode if key in s]
        counts = np.array([p["count"][0] for p in parts], dtype=np.float64)
        means = np.stack([np.asarray(p["mean"], dtype=np.float64) for p in parts])
        stds = np.stack([np.asarray(p["std"], dtype=np.float64) for p in parts])
        shape = (-1,) + (1,) * (means.ndim - 1)
        weights = (counts / counts.sum()).reshape(shape)
        mean = (weights * means).sum(0)
        var = (weights * (stds**2 + (means - mean) ** 2)).sum(0)
        out[key] = {
            "min": np.min(np.stack([np.asarray(p["min"]) for p in parts]), 0).tolist(),
            "max": np.max(np.stack([np.asarray(p["max"]) for p in parts]), 0).tolist(),
            "mean": mean.tolist(),
            "std": np.sqrt(np.maximum(var, 0.0)).tolist(),
            "count": [int(counts.sum())],
        }
    return out


def _tasks_table(tasks: list[str]) -> pa.Table:
    """tasks.parquet: the task text as the (pandas) index, with its task_index, like lerobot writes it."""
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(tasks, pa.string())})
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [
            {"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
             "metadata": {"encoding": "UTF-8"}}
        ],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
             "metadata": None},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object",
             "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    return table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})


def _typed_row_table(row: dict) -> pa.Table:
    """A one-row table of `row`, its trivla/* columns in their EPISODE_COLUMN_TYPES."""
    table = pa.Table.from_pylist([row])
    for i, name in enumerate(table.column_names):
        if name in EPISODE_COLUMN_TYPES:
            table = table.set_column(i, pa.field(name, EPISODE_COLUMN_TYPES[name]),
                                     table.column(i).cast(EPISODE_COLUMN_TYPES[name]))
    return table


def _read_episode_rows(root: Path) -> list[dict]:
    rows = []
    for path in sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet")):
        rows.extend(pq.read_table(path).to_pylist())
    rows.sort(key=lambda r: r["episode_index"])
    return rows


def episode_stats(row: dict) -> dict[str, dict]:
    """One episode's statistics ({feature: {metric: value}}) from its meta/episodes row."""
    stats: dict[str, dict] = {}
    for column, value in row.items():
        if column.startswith("stats/") and value is not None:
            _, rest = column.split("/", 1)
            feature, metric = rest.rsplit("/", 1)
            stats.setdefault(feature, {})[metric] = value
    return stats


# ---------------------------------------------------------------- writer
class LeRobotWriter:
    """Appends episodes to a LeRobot v3.0 dataset, one committed episode at a time (resumable)."""

    def __init__(self, root: str | os.PathLike, *, fps: float, features: dict[str, dict], robot_type: str = "panda"):
        self.root = Path(root)
        self.fps = float(fps)
        self.robot_type = robot_type
        self.features = {**{k: dict(v) for k, v in features.items()}, **DEFAULT_FEATURES}
        for name in features:
            if "/" in name:
                raise ValueError(f"feature name {name!r} must not contain '/'")
        self.video_keys = [k for k, v in self.features.items() if v["dtype"] == "video"]
        self.vector_keys = [k for k, v in features.items() if v["dtype"] != "video"]
        if self.root.exists() and not self.root.is_dir():
            raise NotADatasetError(f"{self.root} is a file, not a dataset folder: choose another --out")
        if (self.root / INFO_PATH).is_file():
            self._open_existing()
        else:
            if self.root.exists() and any(p for p in self.root.iterdir() if not p.name.startswith(".")):
                raise NotADatasetError(
                    f"{self.root} exists and is not empty but has no {INFO_PATH}: not a LeRobot dataset, "
                    "refusing to write into it"
                )
            self.root.mkdir(parents=True, exist_ok=True)
            self._episodes: list[dict] = []
            self._tasks: list[str] = []
            self._checksums: dict[str, str] = {}
            write_checksums(self.root, self._checksums)
            self._write_info()

    def _open_existing(self) -> None:
        path = self.root / INFO_PATH
        try:
            info = json.loads(path.read_text())
            fps, features = float(info["fps"]), dict(info["features"])
        except (ValueError, KeyError, TypeError) as error:
            raise NotADatasetError(f"{path} is not a readable LeRobot info file ({type(error).__name__}: {error}): "
                                   "not a dataset this writer can add to; choose another --out") from error
        if info.get("codebase_version") != CODEBASE_VERSION:
            raise NotADatasetError(f"{self.root}: codebase_version {info.get('codebase_version')!r}, expected {CODEBASE_VERSION}")
        if not math.isclose(fps, self.fps):
            raise ValueError(f"{self.root} was written at fps {fps}, not {self.fps}: use another --out")
        old = {k: (v["dtype"], list(v["shape"])) for k, v in features.items()}
        new = {k: (v["dtype"], list(v["shape"])) for k, v in self.features.items()}
        if old != new:
            raise ValueError(f"{self.root} has features {old}, these episodes have {new}: use another --out")
        self._episodes = _read_episode_rows(self.root)
        for i, row in enumerate(self._episodes):
            if row["episode_index"] != i:
                raise NotADatasetError(f"{self.root}: committed episodes are not numbered 0..N-1 (at {i})")
        tasks_path = self.root / TASKS_PATH
        self._tasks = pq.read_table(tasks_path).column("task").to_pylist() if tasks_path.is_file() else []
        for row in self._episodes:  # tasks.parquet is written before each commit; this is a safety net
            for task in row["tasks"]:
                if task not in self._tasks:
                    self._tasks.append(task)
        committed = [f for row in self._episodes for f in self._files_of(row)]
        recorded = read_checksums(self.root)
        if recorded is None:  # written before checksums were recorded: its files are taken as they are now
            _log.warning("%s has no checksums (written before they were recorded): recording its %d files as they "
                         "are now", self.root, len(committed))
            recorded = {f: file_sha256(self.root / f) for f in committed}
        # An uncommitted episode's entries go: its files are written again.
        self._checksums = {f: recorded[f] for f in committed if f in recorded}
        write_checksums(self.root, self._checksums)
        self._write_info()

    def _files_of(self, row: dict) -> list[str]:
        return _episode_files(row, DATA_PATH, VIDEO_PATH, self.video_keys)

    @property
    def num_episodes(self) -> int:
        return len(self._episodes)

    @property
    def num_frames(self) -> int:
        return int(self._episodes[-1]["dataset_to_index"]) if self._episodes else 0

    def episode_rows(self) -> list[dict]:
        """The committed episodes' metadata rows."""
        return list(self._episodes)

    def add_episode(
        self,
        frames: dict[str, np.ndarray],
        task: str,
        *,
        videos: dict[str, str | os.PathLike | np.ndarray] | None = None,
        video_stats: dict[str, dict] | None = None,
        extra: dict[str, Any] | None = None,
    ) -> int:
        """Commit one episode; returns its index.

        `frames`: feature -> (T, D) array for every non-video feature. `videos`: camera key -> an
        encoded mp4 file (moved into place) or (T, H, W, 3) uint8 frames (encoded here).
        `video_stats`: camera key -> `image_stats` (computed from the frames when they are given).
        `extra`: more JSON-able columns for the episode's metadata row (names like 'trivla/seed').
        """
        from trivla_drake.data.video import write_video

        videos = dict(videos or {})
        video_stats = dict(video_stats or {})
        missing = [k for k in self.vector_keys if k not in frames] + [k for k in self.video_keys if k not in videos]
        if missing:
            raise ValueError(f"episode is missing features {missing}")
        length = len(frames[self.vector_keys[0]])
        if length == 0:
            raise ValueError("an episode needs at least one frame")
        for key in self.vector_keys:
            shape = tuple(self.features[key]["shape"])
            array = np.asarray(frames[key])
            if array.shape != (length,) + shape:
                raise ValueError(f"feature {key!r} has shape {array.shape}, expected {(length,) + shape}")
        index = self.num_episodes
        where = _chunk_file(index)
        start = self.num_frames
        if task not in self._tasks:
            self._tasks.append(task)
            _atomic_write_table(self.root / TASKS_PATH, _tasks_table(self._tasks))
        task_index = self._tasks.index(task)

        row: dict[str, Any] = {
            "episode_index": index,
            "tasks": [task],
            "length": length,
            "data/chunk_index": where["chunk_index"],
            "data/file_index": where["file_index"],
            "dataset_from_index": start,
            "dataset_to_index": start + length,
        }
        for key in self.video_keys:
            target = self.root / VIDEO_PATH.format(video_key=key, **where)
            source = videos[key]
            if isinstance(source, np.ndarray):
                if len(source) != length:
                    raise ValueError(f"video {key!r} has {len(source)} frames, the episode {length}")
                video_stats.setdefault(key, image_stats(source))
                write_video(target, source, self.fps)
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(str(source), str(target))
            row.update(
                {
                    f"videos/{key}/chunk_index": where["chunk_index"],
                    f"videos/{key}/file_index": where["file_index"],
                    f"videos/{key}/from_timestamp": 0.0,
                    f"videos/{key}/to_timestamp": length / self.fps,
                }
            )

        columns: dict[str, pa.Array] = {}
        for key in self.vector_keys:
            feature = self.features[key]
            array = np.asarray(frames[key], dtype=feature["dtype"])
            flat = pa.array(array.reshape(-1))
            columns[key] = pa.FixedSizeListArray.from_arrays(flat, int(feature["shape"][0]))
        columns["timestamp"] = pa.array(np.arange(length, dtype=np.float32) / np.float32(self.fps))
        columns["frame_index"] = pa.array(np.arange(length, dtype=np.int64))
        columns["episode_index"] = pa.array(np.full(length, index, dtype=np.int64))
        columns["index"] = pa.array(np.arange(start, start + length, dtype=np.int64))
        columns["task_index"] = pa.array(np.full(length, task_index, dtype=np.int64))
        _atomic_write_table(self.root / DATA_PATH.format(**where), pa.table(columns))

        stats = {key: array_stats(np.asarray(frames[key])) for key in self.vector_keys}
        stats.update({key: video_stats[key] for key in self.video_keys if key in video_stats})
        for name, values in (
            ("timestamp", columns["timestamp"].to_numpy()[:, None]),
            ("frame_index", np.arange(length)[:, None]),
            ("episode_index", np.full((length, 1), index)),
            ("index", np.arange(start, start + length)[:, None]),
            ("task_index", np.full((length, 1), task_index)),
        ):
            stats[name] = array_stats(values)
        for feature, metrics in stats.items():
            for metric, value in metrics.items():
                row[f"stats/{feature}/{metric}"] = value
        row["meta/episodes/chunk_index"] = where["chunk_index"]
        row["meta/episodes/file_index"] = where["file_index"]
        for key, value in (extra or {}).items():
            row[key] = value
        for name in self._files_of(row):  # recorded before the commit: a committed episode's files always are
            self._checksums[name] = file_sha256(self.root / name)
        write_checksums(self.root, self._checksums)
        # The commit: from here on the episode is part of the dataset.
        _atomic_write_table(self.root / EPISODES_PATH.format(**where), _typed_row_table(row))
        self._episodes.append(row)
        self._write_info()
        return index

    def _write_info(self) -> None:
        n = self.num_episodes
        info = {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": self.robot_type,
            "total_episodes": n,
            "total_frames": self.num_frames,
            "total_tasks": len(self._tasks),
            "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 500,
            "fps": self.fps,
            "splits": {"train": f"0:{n}"},
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if self.video_keys else None,
            "features": self.features,
        }
        _atomic_write_json(self.root / INFO_PATH, info)
        if self._episodes:
            _atomic_write_json(self.root / STATS_PATH, aggregate_stats([episode_stats(r) for r in self._episodes]))
        if not (self.root / TASKS_PATH).is_file():
            _atomic_write_table(self.root / TASKS_PATH, _tasks_table(self._tasks))


# ---------------------------------------------------------------- reader
class LeRobotReader:
    """Reads a LeRobot v3.0 dataset folder: metadata, per-episode frames and decoded videos."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        if not self.root.is_dir():
            raise NotADatasetError(f"{self.root} is not a LeRobot dataset: no such directory")
        info_path = self.root / INFO_PATH
        if not info_path.is_file():
            raise NotADatasetError(f"{self.root} is not a LeRobot dataset: {INFO_PATH} is missing")
        try:
            self.info = json.loads(info_path.read_text())
            self.fps = float(self.info["fps"])
            self.features = self.info["features"]
            self.data_path = self.info["data_path"]
            self.video_path = self.info.get("video_path")
        except (ValueError, KeyError, TypeError) as error:
            raise NotADatasetError(f"{self.root} is not a LeRobot dataset: {INFO_PATH} is unreadable ({error})") from error
        if not str(self.info.get("codebase_version", "")).startswith("v3"):
            raise NotADatasetError(
                f"{self.root}: codebase_version {self.info.get('codebase_version')!r} is not supported (v3.x only)"
            )
        try:
            self.episodes = _read_episode_rows(self.root)
            tasks_path = self.root / TASKS_PATH
            self.tasks = pq.read_table(tasks_path).column("task").to_pylist() if tasks_path.is_file() else []
        except (OSError, pa.ArrowException) as error:
            raise NotADatasetError(f"{self.root}: cannot read the dataset's metadata ({error})") from error
        stats_path = self.root / STATS_PATH
        self.stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
        self.camera_keys = [k for k, v in self.features.items() if v["dtype"] == "video"]
        self.checksums = read_checksums(self.root)  # None: written before checksums were recorded
        self._digests: dict[int, dict[str, str]] = {}

    def episode_files(self, episode_index: int) -> list[str]:
        """The data and video files (paths relative to the folder) holding one episode."""
        return _episode_files(self.episodes[episode_index], self.data_path, self.video_path, self.camera_keys)

    def episode_digests(self, episode_index: int) -> dict[str, str]:
        """sha256 of each of the episode's files (`episode_files`), checked against meta/checksums.json:
        DatasetCorruptError naming a file that is missing or changed since it was written. A dataset written
        before checksums were recorded is hashed unchecked, with a one-line warning (once)."""
        if episode_index not in self._digests:
            files = self.episode_files(episode_index)
            if self.checksums is None:
                if not self._digests:
                    _log.warning("dataset %s records no checksums (written before they were): its files cannot be "
                                 "checked for corruption; `%s %s` records them", self.root, RECORD_COMMAND, self.root)
                self._digests[episode_index] = {f: file_sha256(self.root / f) for f in files}
            else:
                self._digests[episode_index] = {f: check_file(self.root, f, self.checksums) for f in files}
        return self._digests[episode_index]

    def verify_files(self, episodes: list[int] | None = None) -> None:
        """Checks the files of `episodes` (all: None) against their recorded checksums (`episode_digests`)."""
        for episode in range(self.num_episodes) if episodes is None else episodes:
            self.episode_digests(episode)

    @property
    def num_episodes(self) -> int:
        return len(self.episodes)

    @property
    def num_frames(self) -> int:
        return int(sum(e["length"] for e in self.episodes))

    def episode_frames(self, episode_index: int) -> dict[str, np.ndarray]:
        """Every non-video column of one episode: name -> (T,) or (T, D) array."""
        row = self.episodes[episode_index]
        path = self.root / self.data_path.format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])
        table = pq.read_table(path)
        index = table.column("index").to_numpy()
        keep = np.flatnonzero((index >= row["dataset_from_index"]) & (index < row["dataset_to_index"]))
        table = table.take(pa.array(keep))
        out: dict[str, np.ndarray] = {}
        for name in table.column_names:
            column = table.column(name).combine_chunks()
            if pa.types.is_fixed_size_list(column.type):
                out[name] = column.flatten().to_numpy(zero_copy_only=False).reshape(len(column), column.type.list_size)
            elif pa.types.is_list(column.type):
                out[name] = np.stack(column.to_numpy(zero_copy_only=False)) if len(column) else np.empty((0,))
            else:
                out[name] = column.to_numpy(zero_copy_only=False)
        return out

    def episode_video(self, episode_index: int, key: str) -> np.ndarray:
        """All frames of one camera for one episode, (T, H, W, 3) uint8."""
        from trivla_drake.data.video import read_video

        if key not in self.camera_keys:
            raise ValueError(f"unknown camera {key!r}; this dataset has {self.camera_keys}")
        row = self.episodes[episode_index]
        path = self.root / self.video_path.format(
            video_key=key, chunk_index=row[f"videos/{key}/chunk_index"], file_index=row[f"videos/{key}/file_index"]
        )
        frames = read_video(path)
        first = int(round(row[f"videos/{key}/from_timestamp"] * self.fps))
        return frames[first : first + int(row["length"])]

    def task_of(self, episode_index: int) -> str:
        return self.episodes[episode_index]["tasks"][0]
