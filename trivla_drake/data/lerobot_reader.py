"""Reading a LeRobot v3.0 dataset folder (the layout: lerobot_format.py): metadata, frames, decoded videos."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from trivla_drake.data.checksums import RECORD_COMMAND, check_file, file_sha256, read_checksums
from trivla_drake.data.lerobot_format import (
    INFO_PATH,
    STATS_PATH,
    TASKS_PATH,
    NotADatasetError,
    episode_files,
    read_episode_rows,
)

_log = logging.getLogger(__name__)


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
            self.episodes = read_episode_rows(self.root)
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
        return episode_files(self.episodes[episode_index], self.data_path, self.video_path, self.camera_keys)

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
