"""Appending episodes to a LeRobot v3.0 dataset (the layout: lerobot_format.py), with pyarrow and OpenCV only.

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

from trivla_drake.data.checksums import file_sha256, read_checksums, write_checksums
from trivla_drake.data.durable import atomic_write_text, fsync_file
from trivla_drake.data.lerobot_format import (
    CHUNKS_SIZE,
    CODEBASE_VERSION,
    DATA_PATH,
    DEFAULT_FEATURES,
    EPISODE_COLUMN_TYPES,
    EPISODES_PATH,
    INFO_PATH,
    STATS_PATH,
    TASKS_PATH,
    VIDEO_PATH,
    NotADatasetError,
    episode_files,
    read_episode_rows,
)
from trivla_drake.data.lerobot_stats import aggregate_stats, array_stats, episode_stats, image_stats

_log = logging.getLogger(__name__)


def _atomic_write_json(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2))


def _atomic_write_table(path: Path, table: pa.Table) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(table, tmp)
    fsync_file(tmp)  # meta/episodes commits an episode: never an empty file under its name
    os.replace(tmp, path)


def _chunk_file(episode_index: int) -> dict[str, int]:
    return {"chunk_index": episode_index // CHUNKS_SIZE, "file_index": episode_index % CHUNKS_SIZE}


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
        self._episodes = read_episode_rows(self.root)
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
        return episode_files(row, DATA_PATH, VIDEO_PATH, self.video_keys)

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
