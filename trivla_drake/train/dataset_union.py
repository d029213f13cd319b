"""Training the policy stage on several LeRobot datasets at once (`data` A, `extra_data` [B, ...]).

- `episode_content_key`: what an episode is, without where it lies in its folder (its index, its file and
  frame offsets): two folders collected with the same seed hold equal episodes under different indices. It
  hashes the metadata row (`episode_row_key`), the frames and the videos, so a replaced episode file is a new episode.
- `drop_repeated_episodes`: each episode once, the first folder's copy kept; `check_each_folder_adds`.
- `check_same_features`: every folder records the same non-video features (a batch mixes their samples).
- `union_normalization`: the state and action statistics of all the folders together, each episode once
  (per-episode statistics, weighted by their frame counts), as one folder holding them all would give.
- `PolicyDatasetUnion`: the samples of one `PolicyFeatureDataset` per folder, one after another (a ConcatDataset).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch.utils.data

from trivla_drake.data.lerobot_format import EPISODE_COLUMN_DEFAULTS, REMOVED_EPISODE_COLUMNS
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_stats import aggregate_stats, episode_stats
from trivla_drake.nn.config import TriVLAConfig
from trivla_drake.nn.normalization import NormalizationStats

# Episode metadata that says where an episode is stored, not what it holds.
_LOCATING_KEYS = ("episode_index", "dataset_from_index", "dataset_to_index")
_LOCATING_PREFIXES = ("data/", "videos/", "meta/", "stats/episode_index/", "stats/index/", "stats/task_index/")
# The frame columns that say where an episode is stored (its index, its frames' indices in the folder, its task's
# index in meta/tasks), not what it holds.
_LOCATING_COLUMNS = ("episode_index", "index", "task_index")
# Episode columns left out of the key at these values: rows written before a column existed, or after it was removed,
# lack it.
_UNSET_COLUMNS = {**EPISODE_COLUMN_DEFAULTS, **REMOVED_EPISODE_COLUMNS}


def episode_row_key(reader: LeRobotReader, episode: int) -> str:
    """A hash of episode `episode`'s metadata row without the entries that locate it in its folder
    (index, files, offsets, and the statistics of the index columns): equal for the same episode
    written into two folders."""
    row = {k: v for k, v in reader.episodes[episode].items()
           if k not in _LOCATING_KEYS and not k.startswith(_LOCATING_PREFIXES)
           and not (k in _UNSET_COLUMNS and v == _UNSET_COLUMNS[k])}  # as written before they were, or after removal
    return hashlib.sha256(json.dumps(row, sort_keys=True, default=str).encode()).hexdigest()[:16]


def episode_content_key(reader: LeRobotReader, episode: int) -> str:
    """A hash of what episode `episode` holds, not where it lies in its folder: its metadata row
    (`episode_row_key`), its frames without the columns that locate them, and the sha256 of its videos (an
    episode's own mp4 files, as `collect` writes them; `episode_digests` checks its files against the dataset's
    recorded checksums first). Equal for the same episode written into two folders; a file of it replaced (its
    checksums recorded again, its metadata row kept) makes it another episode.

    Not `episode_content_fingerprint` (the feature cache's name of an episode): that hashes the episode's index,
    and its data file, which records the index in every frame, so the same episode at another index would differ.
    """
    digests = reader.episode_digests(episode)
    hasher = hashlib.sha256(episode_row_key(reader, episode).encode())
    frames = reader.episode_frames(episode)
    for name in sorted(set(frames) - set(_LOCATING_COLUMNS)):
        column = np.ascontiguousarray(frames[name])
        hasher.update(f"{name}:{column.dtype.str}:{column.shape}:".encode() + column.tobytes())
    for path in reader.episode_files(episode)[1:]:  # the data file first, then one video per camera
        hasher.update(digests[path].encode())
    return hasher.hexdigest()[:16]


def drop_repeated_episodes(readers: list[LeRobotReader], episodes: list[list[int]]) -> tuple[list[list[int]], int]:
    """`episodes` (one list per reader) without the episodes an earlier reader's list already holds
    (`episode_content_key`; a folder's own episodes are all kept), and how many were dropped."""
    if len(readers) == 1:
        return [list(chosen) for chosen in episodes], 0  # nothing earlier to repeat
    seen: set[str] = set()
    kept: list[list[int]] = []
    for reader, chosen in zip(readers, episodes):
        keys = {episode: episode_content_key(reader, episode) for episode in chosen}
        kept.append([episode for episode in chosen if keys[episode] not in seen])
        seen.update(keys.values())
    return kept, sum(map(len, episodes)) - sum(map(len, kept))


def check_each_folder_adds(readers: list[LeRobotReader], kept: list[list[int]]) -> None:
    """Raises ValueError naming an extra_data folder none of whose chosen episodes is new (all held by an
    earlier folder): most likely a copy of --data, given by mistake."""
    for reader, episodes in zip(readers[1:], kept[1:]):
        if not episodes:
            raise ValueError(f"extra_data: dataset {reader.root} adds no episode that --data "
                             f"{readers[0].root} or an earlier extra_data folder does not already hold")


def check_same_features(readers: list[LeRobotReader]) -> None:
    """Raises ValueError naming the first folder whose non-video features (state, action, tcp pose, ...)
    differ from --data's: a batch mixes the folders' samples, so each must carry the same fields."""
    def fields(reader):
        return {k for k, v in reader.features.items() if v.get("dtype") != "video"}

    first = fields(readers[0])
    for reader in readers[1:]:
        mine = fields(reader)
        if mine != first:
            detail = "; ".join(part for part in (
                f"has {sorted(mine - first)} that --data lacks" if mine - first else "",
                f"lacks {sorted(first - mine)}" if first - mine else "") if part)
            raise ValueError(f"extra_data: dataset {reader.root} {detail} (--data "
                             f"{readers[0].root}); train together only folders recorded with the same fields")


def check_same_fps(readers: list[LeRobotReader]) -> None:
    """Raises ValueError naming the first folder whose frame rate differs from the first's (action chunks
    and the gripper-event window are counted in frames)."""
    first = readers[0]
    for reader in readers[1:]:
        if float(reader.fps) != float(first.fps):
            raise ValueError(f"extra_data: dataset {reader.root} is recorded at {reader.fps} fps "
                             f"but --data {first.root} at {first.fps} fps; the action chunks would mean other times")


def union_normalization(readers: list[LeRobotReader], config: TriVLAConfig) -> NormalizationStats:
    """State mean / std and action min / max over all `readers`' episodes together, each episode once: the
    first folder's meta/stats.json (all its episodes, as a run on it alone) and the per-episode statistics of
    the episodes each later folder adds (those no earlier folder holds)."""
    from trivla_drake.train.datasets import ACTION_KEY, STATE_KEY, normalization_from_stats

    if len(readers) == 1:
        return normalization_from_stats(readers[0], config)
    for reader in readers:
        normalization_from_stats(reader, config)  # each folder's statistics are there and well formed
    every = [list(range(reader.num_episodes)) for reader in readers]
    added, _ = drop_repeated_episodes(readers, every)
    parts = [{k: readers[0].stats[k] for k in (STATE_KEY, ACTION_KEY)}]
    for reader, episodes in zip(readers[1:], added[1:]):
        for episode in episodes:
            stats = episode_stats(reader.episodes[episode])
            parts.append({k: stats[k] for k in (STATE_KEY, ACTION_KEY)})
    merged = aggregate_stats(parts)
    result = NormalizationStats.from_dict({
        "state_mean": merged[STATE_KEY]["mean"], "state_std": merged[STATE_KEY]["std"],
        "action_min": merged[ACTION_KEY]["min"], "action_max": merged[ACTION_KEY]["max"],
    })
    result.check_dims(config.policy.state_dim, config.policy.action_dim)
    return result


class PolicyDatasetUnion(torch.utils.data.ConcatDataset):
    """The samples of `parts` (PolicyFeatureDataset, one per folder) one after another (torch's ConcatDataset),
    with what the trainer reads of a part: `shards`, keyed (part, episode)."""

    def __init__(self, parts: list[Any]) -> None:
        super().__init__(parts)
        self.shards: dict[tuple[int, int], Path] = {
            (i, episode): path for i, part in enumerate(parts) for episode, path in part.shards.items()
        }
