"""Appending episodes to a LeRobot v3.0 dataset (the layout: lerobot_format.py), with pyarrow, OpenCV and PyAV.

Atomicity: an episode's videos, data and (new) task rows are written first, each through a temporary
file renamed into place, then meta/checksums.json with their checksums added; its `meta/episodes` file
is written last and is the commit. A process killed
at any moment leaves every committed episode readable; `LeRobotWriter` reopens the folder, ignores
anything of an uncommitted episode (it is overwritten) and rebuilds info.json and stats.json from
the committed episodes' metadata.

One dataset, one schema: its videos are all in one codec (info.json's video.codec, set from the first committed
episode's files, or by `video_codec`), and its statistics carry the quantiles (lerobot_stats.py) unless its first
episode was written before they were recorded (then none of its episodes records them, so every meta/episodes
file has the same columns, as lerobot's readers need).
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
    info_fps,
    read_episode_rows,
)
from trivla_drake.data.lerobot_stats import (
    QUANTILES,
    aggregate_stats,
    array_stats,
    episode_stats,
    has_quantiles,
    image_stats,
    without_quantiles,
)

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


def _records_quantiles(row: dict) -> bool:
    """Whether an episode's meta/episodes row has quantile statistics (rows written before them have none)."""
    return any(column.startswith("stats/") and column.rsplit("/", 1)[-1] in QUANTILES for column in row)


class LeRobotWriter:
    """Appends episodes to a LeRobot v3.0 dataset, one committed episode at a time (resumable).

    `video_codec` (one of data/video.py's VIDEO_CODECS): the codec of the videos this writer encodes from frames,
    and the only one it accepts in files; ValueError naming it where the dataset holds videos of another. None: the
    dataset's codec where it has episodes, else the features' video.codec ('mpeg4' by default) until the first
    episode's files fix it.
    """

    def __init__(self, root: str | os.PathLike, *, fps: float, features: dict[str, dict], robot_type: str = "panda",
                 video_codec: str | None = None):
        self.root = Path(root)
        info_fps(fps)  # a clear error for a rate lerobot cannot record
        self.fps = float(fps)
        self.robot_type = robot_type
        self.features = {**{k: dict(v) for k, v in features.items()}, **DEFAULT_FEATURES}
        for name in features:
            if "/" in name:
                raise ValueError(f"feature name {name!r} must not contain '/'")
        self.video_keys = [k for k, v in self.features.items() if v["dtype"] == "video"]
        self.vector_keys = [k for k, v in features.items() if v["dtype"] != "video"]
        for key in self.video_keys:
            self.features[key]["info"] = dict(self.features[key].get("info") or {})
        if video_codec is not None:
            from trivla_drake.data.video import video_encoder

            video_encoder(video_codec)  # ValueError naming video_codec for an unknown or unavailable codec
        self._codec_fixed = video_codec is not None
        self.video_codec = video_codec or self._declared_codec()
        self.records_quantiles = True
        self._set_video_info({"codec": self.video_codec})
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

    def _declared_codec(self) -> str:
        """The codec the features' info blocks name ('mpeg4' where they name none)."""
        codecs = {self.features[k]["info"].get("video.codec", "mpeg4") for k in self.video_keys}
        return codecs.pop() if len(codecs) == 1 else "mpeg4"

    def _set_video_info(self, probe: dict) -> None:
        """Records a video's codec (and pix_fmt, where known) in every camera's info block: one codec per dataset."""
        for key in self.video_keys:
            self.features[key]["info"]["video.codec"] = probe["codec"]
            if "pix_fmt" in probe:
                self.features[key]["info"]["video.pix_fmt"] = probe["pix_fmt"]

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
        if self._episodes:
            self._adopt_dataset_schema(features)
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

    def _adopt_dataset_schema(self, features: dict[str, dict]) -> None:
        """Takes the committed episodes' video info (codec, pix_fmt: what their files are) and statistics schema
        from the dataset's info.json `features`; ValueError naming video_codec where this writer was asked for
        another codec."""
        if self.video_keys:
            old = features[self.video_keys[0]].get("info") or {}
            codec = old.get("video.codec", "mpeg4")  # every video before the choice was mpeg4
            if self._codec_fixed and codec != self.video_codec:
                raise ValueError(
                    f"video_codec {self.video_codec!r}: {self.root} holds {len(self._episodes)} episodes of "
                    f"{codec!r} video (meta/info.json); one dataset holds one codec: resume it with video_codec "
                    f"{codec!r}, or write to another --out")
            self.video_codec, self._codec_fixed = codec, True
            self._set_video_info({"codec": codec, "pix_fmt": old.get("video.pix_fmt", "yuv420p")})
        self.records_quantiles = _records_quantiles(self._episodes[0])
        if not self.records_quantiles:
            _log.warning("%s was written before quantile statistics were recorded: its new episodes record none "
                         "either (one schema per dataset), and meta/stats.json has min/max/mean/std/count only",
                         self.root)

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
        Files must be in the dataset's codec (`video_codec`) and hold the episode's frames at the camera's size.
        `video_stats`: camera key -> `image_stats` (computed from the frames when they are given; with the
        quantiles unless the dataset records none, `records_quantiles`).
        `extra`: more JSON-able columns for the episode's metadata row (names like 'trivla/seed').
        """
        from trivla_drake.data.video import PIX_FMT, write_video

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
        probe = self._check_videos(videos, length)
        codec = probe["codec"] if probe else self.video_codec
        for key in list(video_stats):
            if not self.records_quantiles:
                video_stats[key] = without_quantiles(video_stats[key])
            elif not has_quantiles(video_stats[key]):
                raise ValueError(f"video_stats[{key!r}] has no quantiles {list(QUANTILES)}: compute it with "
                                 "lerobot_stats.image_stats")
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
            if isinstance(source, np.ndarray):  # its length was checked (_check_videos)
                video_stats.setdefault(key, image_stats(source, quantiles=self.records_quantiles))
                write_video(target, source, self.fps, codec)
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

        stats = {key: array_stats(np.asarray(frames[key]), quantiles=self.records_quantiles)
                 for key in self.vector_keys}
        stats.update({key: video_stats[key] for key in self.video_keys if key in video_stats})
        for name, values in (
            ("timestamp", columns["timestamp"].to_numpy()[:, None]),
            ("frame_index", np.arange(length)[:, None]),
            ("episode_index", np.full((length, 1), index)),
            ("index", np.arange(start, start + length)[:, None]),
            ("task_index", np.full((length, 1), task_index)),
        ):
            stats[name] = array_stats(values, quantiles=self.records_quantiles)
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
        if self.video_keys and not self._codec_fixed:  # the first episode's files fix the dataset's codec
            self.video_codec, self._codec_fixed = codec, True
            self._set_video_info(probe or {"codec": codec, "pix_fmt": PIX_FMT})
        self._write_info()
        return index

    def _check_videos(self, videos: dict, length: int) -> dict | None:
        """Checks an episode's videos before anything is written: frames give `length` frames; files are in the
        dataset's codec (or, before its first episode, all in one) at the camera's size, with `length` frames.
        Returns the files' probe (data/video.py's `probe_video`; None: no files)."""
        from trivla_drake.data.video import probe_video

        first = None
        for key in self.video_keys:
            source = videos[key]
            if isinstance(source, np.ndarray):
                if len(source) != length:
                    raise ValueError(f"video {key!r} has {len(source)} frames, the episode {length}")
                continue
            probe = probe_video(source)
            expected = first["codec"] if first else self.video_codec if self._codec_fixed else probe["codec"]
            if probe["codec"] != expected:
                held = f"{self.root} holds {expected!r} video (meta/info.json)" if self._codec_fixed else \
                    f"its other camera's is {expected!r}"
                raise ValueError(f"video_codec: {key!r} video {source} is {probe['codec']!r} but {held}; one dataset "
                                 f"holds one codec: write it with video_codec {expected!r}, or to another --out")
            height, width = self.features[key]["shape"][:2]
            if (probe["height"], probe["width"]) != (height, width):
                raise ValueError(f"video {key!r} ({source}) is {probe['width']}x{probe['height']}, the camera "
                                 f"{width}x{height}")
            if probe["frames"] and probe["frames"] != length:
                raise ValueError(f"video {key!r} ({source}) has {probe['frames']} frames, the episode {length}")
            first = first or probe
        return first

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
            "fps": info_fps(self.fps),
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
