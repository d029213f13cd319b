"""What each stage trains on, from a LeRobot dataset (video, policy) or the generated VQA set (vlm).

- `VideoClipDataset`: clips of `num_frames` frames (the current frame, then future frames
  `future_stride` apart) of one camera view, from frames decoded once and cached at System 3's
  video size (`FrameStore`).
- `PolicyFeatureDataset`: state, action chunk and the cached System 2/3 features of one frame.
- helpers: normalisation statistics from meta/stats.json, and the
  checks that the dataset matches the model's state and action spaces.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from trivla_drake.data.lerobot_format import with_removed_columns
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.samples import TrainingSamples
from trivla_drake.nn.config import TriVLAConfig
from trivla_drake.nn.normalization import NormalizationStats

STATE_KEY = "observation.state"
ACTION_KEY = "action"


# ---------------------------------------------------------------------------------------------
# Dataset-level helpers


def episode_fingerprint(reader: LeRobotReader, episode: int) -> str:
    """A hash of an episode's metadata row (length, task, file indices, per-episode statistics of every
    feature and camera): changes whenever the episode's content does, not when the folder moves. A row written
    without the columns of removed collection experiments hashes as it was written with them (`with_removed_columns`)."""
    row = with_removed_columns(reader.episodes[episode])
    payload = json.dumps(row, sort_keys=True, default=str).encode()
    cameras = json.dumps({k: reader.features[k].get("shape") for k in reader.camera_keys}, sort_keys=True).encode()
    return hashlib.sha256(payload + cameras).hexdigest()[:16]


def episode_content_fingerprint(reader: LeRobotReader, episode: int) -> str:
    """`episode_fingerprint` and the sha256 of the episode's data and video files (checked against the dataset's
    recorded checksums): the name of what is cached from an episode, so a replaced file is never read stale."""
    digests = json.dumps(reader.episode_digests(episode), sort_keys=True).encode()
    return hashlib.sha256(episode_fingerprint(reader, episode).encode() + digests).hexdigest()[:16]


def _feature_names(reader: LeRobotReader, key: str) -> tuple[int, list[str] | None]:
    if key not in reader.features:
        raise ValueError(f"dataset {reader.root} has no feature {key!r}; it has {sorted(reader.features)}")
    feature = reader.features[key]
    shape = feature.get("shape") or [0]
    names = feature.get("names")
    return int(shape[0]), (list(names) if isinstance(names, list) else None)


def check_spaces(reader: LeRobotReader, config: TriVLAConfig, where: str) -> None:
    """Raises ValueError when the dataset's state or action vectors do not match the model's
    (dimension, then names when the dataset records them). `where` names the model in the message."""
    pol = config.policy
    for key, dim, names, what in (
        (ACTION_KEY, pol.action_dim, config.action_names, "action"),
        (STATE_KEY, pol.state_dim, config.state_names, "state"),
    ):
        data_dim, data_names = _feature_names(reader, key)
        if data_dim != dim:
            raise ValueError(
                f"{where} has a {dim}-D {what} space but dataset {reader.root} has {data_dim}-D {key!r}: "
                "another action space; train a model made for this dataset"
            )
        if data_names is not None and list(names) != data_names:
            raise ValueError(
                f"{where} has {what} names {list(names)} but dataset {reader.root} has {data_names}: "
                "another action space"
            )


def normalization_from_stats(reader: LeRobotReader, config: TriVLAConfig) -> NormalizationStats:
    """Normalisation statistics from meta/stats.json: state mean/std, action min/max."""
    stats = reader.stats
    missing = [k for k in (STATE_KEY, ACTION_KEY) if k not in stats]
    if missing:
        raise ValueError(f"dataset {reader.root}: meta/stats.json has no statistics for {missing}")
    try:
        result = NormalizationStats.from_dict(
            {
                "state_mean": stats[STATE_KEY]["mean"],
                "state_std": stats[STATE_KEY]["std"],
                "action_min": stats[ACTION_KEY]["min"],
                "action_max": stats[ACTION_KEY]["max"],
            }
        )
    except (KeyError, ValueError) as exc:
        raise ValueError(f"dataset {reader.root}: meta/stats.json is malformed: {exc}") from exc
    result.check_dims(config.policy.state_dim, config.policy.action_dim)
    return result


def narrowed_action_ranges(old: NormalizationStats, new: NormalizationStats, names: list[str] | tuple[str, ...],
                           ratio: float = 0.8) -> list[str]:
    """The action dimensions whose [min, max] range in `new` is under `ratio` of its width in `old`, as
    "name [old min, old max] -> [new min, new max]": where refitting the statistics of a checkpoint to a
    smaller dataset rescales what its outputs mean (a follow run that starts from that checkpoint)."""
    changed = []
    for i, (lo, hi, nlo, nhi) in enumerate(zip(old.action_min, old.action_max, new.action_min, new.action_max)):
        if (nhi - nlo) < ratio * (hi - lo):
            name = names[i] if i < len(names) else str(i)
            changed.append(f"{name} [{lo:.4g}, {hi:.4g}] -> [{nlo:.4g}, {nhi:.4g}]")
    return changed


def check_cameras(reader: LeRobotReader, cameras: list[str]) -> None:
    """Raises ValueError naming a camera the dataset lacks."""
    missing = [c for c in cameras if c not in reader.camera_keys]
    if missing:
        raise ValueError(
            f"dataset {reader.root} has no camera {missing[0]!r} (cameras: {reader.camera_keys}); "
            "set static_camera / wrist_camera"
        )


def resize_frames(frames: np.ndarray, size: int, *, chunk: int = 64) -> np.ndarray:
    """uint8 (N, H, W, 3) -> uint8 (N, size, size, 3) with antialiased bilinear resizing (what
    System 3's VAE input does); frames already at that size are returned unchanged."""
    frames = np.asarray(frames)
    if frames.shape[1] == size and frames.shape[2] == size:
        return frames
    out = np.empty((len(frames), size, size, 3), dtype=np.uint8)
    for start in range(0, len(frames), chunk):
        x = torch.from_numpy(np.ascontiguousarray(frames[start : start + chunk])).permute(0, 3, 1, 2).float()
        y = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
        out[start : start + chunk] = y.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()
    return out


def atomic_save_npy(path: Path, array: np.ndarray) -> None:
    """np.save through a temporary file renamed into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    with open(tmp, "wb") as f:
        np.save(f, array)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class _LRU:
    """A small least-recently-used cache of opened files (memory maps, safetensors handles)."""

    def __init__(self, opener: Callable[[Path], Any], size: int = 32) -> None:
        self._opener, self._size = opener, size
        self._items: OrderedDict[Path, Any] = OrderedDict()

    def get(self, path: Path) -> Any:
        if path in self._items:
            self._items.move_to_end(path)
            return self._items[path]
        value = self._opener(path)
        self._items[path] = value
        if len(self._items) > self._size:
            self._items.popitem(last=False)
        return value

    def __getstate__(self):  # DataLoader workers open their own files
        return {"_opener": self._opener, "_size": self._size, "_items": OrderedDict()}


# ---------------------------------------------------------------------------------------------
# Video stage


class FrameStore:
    """Decoded camera frames resized to `size`, one .npy per (episode, camera) in `root`, memory-mapped.
    Files are named by the episode's content (`episode_content_fingerprint`), so they are made once and shared
    across runs, and a replaced video is decoded again."""

    def __init__(self, reader: LeRobotReader, cameras: list[str], size: int, root: str | os.PathLike) -> None:
        check_cameras(reader, cameras)
        self.reader, self.cameras, self.size = reader, list(cameras), int(size)
        self.root = Path(root) / f"frames-{self.size}"
        self._fingerprints: dict[int, str] = {}
        self._maps = _LRU(lambda p: np.load(p, mmap_mode="r"), size=32)

    def path(self, episode: int, camera: str) -> Path:
        """The .npy file of one episode's camera."""
        if episode not in self._fingerprints:
            self._fingerprints[episode] = episode_content_fingerprint(self.reader, episode)
        return self.root / f"{self._fingerprints[episode]}-{camera.replace('/', '_')}.npy"

    def missing(self, episodes: list[int]) -> list[tuple[int, str]]:
        """(episode, camera) pairs not decoded yet."""
        return [(e, c) for e in episodes for c in self.cameras if not self.path(e, c).is_file()]

    def make(self, episode: int, camera: str) -> None:
        """Decodes, resizes and stores one episode's camera."""
        frames = resize_frames(self.reader.episode_video(episode, camera), self.size)
        length = int(self.reader.episodes[episode]["length"])
        if len(frames) < length:
            raise ValueError(f"dataset {self.reader.root}: episode {episode}'s {camera} video has {len(frames)} "
                             f"frames, the episode {length}")
        atomic_save_npy(self.path(episode, camera), frames)

    def frames(self, episode: int, camera: str) -> np.ndarray:
        """uint8 (T, size, size, 3), memory-mapped."""
        return self._maps.get(self.path(episode, camera))


class VideoClipDataset:
    """Clips for eq. (1): `num_frames` frames t, t + s, ..., t + (num_frames - 1) s of one camera (frame 0
    is the current frame), for every start t whose whole clip lies inside its episode, and each camera."""

    def __init__(self, store: FrameStore, episodes: list[int], num_frames: int, stride: int) -> None:
        self.store, self.num_frames, self.stride = store, int(num_frames), int(stride)
        span = (self.num_frames - 1) * self.stride
        rows = []
        for episode in episodes:
            length = int(store.reader.episodes[episode]["length"])
            for cam_index in range(len(store.cameras)):
                for t in range(0, length - span):
                    rows.append((episode, cam_index, t))
        if not rows:
            raise ValueError(
                f"no episode is long enough for a clip of {self.num_frames} frames {self.stride} apart "
                f"({span + 1} frames); lower clip_seconds or future_stride"
            )
        self.index = np.asarray(rows, dtype=np.int64)
        self._tasks = {e: store.reader.task_of(e) for e in episodes}

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Any]:
        episode, cam_index, t = (int(v) for v in self.index[i])
        frames = self.store.frames(episode, self.store.cameras[cam_index])
        clip = np.asarray(frames[t + self.stride * np.arange(self.num_frames)])
        return {"video": clip, "instruction": self._tasks[episode]}


def collate_video(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Batch for `TriVLA.compute_video_loss`."""
    return {
        "video": torch.from_numpy(np.stack([it["video"] for it in items])),
        "instruction": [it["instruction"] for it in items],
    }


def clip_stride(fps: float, num_frames: int, clip_seconds: float) -> int:
    """Frames between clip frames so that `num_frames` frames span about `clip_seconds`."""
    return max(1, int(round(fps * clip_seconds / max(1, num_frames - 1))))


# ---------------------------------------------------------------------------------------------
# Policy stage


class PolicyFeatureDataset:
    """One sample per cached frame (every `feature_stride`-th frame of each episode): the current
    state, the action chunk from that frame (padded past the end with holds, `action_is_pad`; entries
    after a disturbed step of a DART demonstration, `action_is_stale`; neither counts), and
    the frame's cached Q_vl and F_p (static, wrist) when Systems 2 / 3 are on. With `grounding_frames_only`,
    only the frames that train the instruction grounding (`TrainingSamples.grounding_frames`: before each
    episode's first gripper change, and the carrying frames of `grounding_carry_tasks`; the bind phase; the
    dataset needs observation.tcp_pose)."""

    def __init__(
        self,
        reader: LeRobotReader,
        episodes: list[int],
        shards: dict[int, Path],
        *,
        feature_stride: int,
        action_horizon: int,
        use_system2: bool,
        use_system3: bool,
        grounding_frames_only: bool = False,
        grounding_carry_tasks: tuple[str, ...] = (),
    ) -> None:
        self.samples = TrainingSamples(
            reader, history=1, future_frames=0, chunk_size=action_horizon, cameras=[],
            cache_episodes=max(1, len(episodes)), grounding_carry_tasks=grounding_carry_tasks,
        )
        self.shards, self.use_system2, self.use_system3 = shards, use_system2, use_system3
        lengths = [int(e["length"]) for e in reader.episodes]
        self._starts = np.concatenate([[0], np.cumsum(lengths)])  # TrainingSamples' global frame index
        rows = []
        for episode in episodes:
            length = int(reader.episodes[episode]["length"])
            grounding = self.samples.grounding_frames(episode) if grounding_frames_only else None
            for row, t in enumerate(range(0, length, feature_stride)):
                if grounding is None or grounding[t]:
                    rows.append((episode, t, row))
        if not rows:
            raise ValueError("the selected episodes have no frames"
                             + (" that train the grounding (before a gripper change)" if grounding_frames_only else ""))
        self.index = np.asarray(rows, dtype=np.int64)
        self._handles = _LRU(_open_safetensors, size=32)

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Any]:
        episode, t, row = (int(v) for v in self.index[i])
        sample = self.samples[int(self._starts[episode]) + t]
        item: dict[str, Any] = {
            "state": torch.from_numpy(np.asarray(sample[STATE_KEY][-1], dtype=np.float32)),
            "action": torch.from_numpy(np.asarray(sample[ACTION_KEY], dtype=np.float32)),
            "action_is_pad": torch.from_numpy(np.asarray(sample["action_is_pad"], dtype=bool)),
            "action_is_stale": torch.from_numpy(np.asarray(sample["action_is_stale"], dtype=bool)),
        }
        if "subgoal_position" in sample:
            item["subgoal_position"] = torch.from_numpy(np.asarray(sample["subgoal_position"], dtype=np.float32))
            item["subgoal_in_loss"] = torch.tensor(bool(sample["subgoal_in_loss"]))
        if self.use_system2 or self.use_system3:
            handle = self._handles.get(self.shards[episode])
            if self.use_system2:
                item["q_vl"] = handle.get_slice("q_vl")[row : row + 1][0]
            if self.use_system3:
                item["dynamics_static"] = handle.get_slice("dynamics_static")[row : row + 1][0]
                item["dynamics_wrist"] = handle.get_slice("dynamics_wrist")[row : row + 1][0]
        return item


def _open_safetensors(path: Path):
    from safetensors import safe_open

    return safe_open(str(path), framework="pt", device="cpu")


def collate_policy(items: list[dict[str, Any]]) -> dict[str, Any]:
    """Batch for `TriVLA.compute_loss` with precomputed features: Q_vl right-padded to the longest
    sequence with `q_vl_mask`, features as float32."""
    batch: dict[str, Any] = {
        key: torch.stack([it[key] for it in items]) for key in ("state", "action", "action_is_pad", "action_is_stale")
    }
    if "q_vl" in items[0]:
        longest = max(it["q_vl"].shape[0] for it in items)
        dim = items[0]["q_vl"].shape[1]
        q_vl = torch.zeros(len(items), longest, dim, dtype=torch.float32)
        mask = torch.zeros(len(items), longest, dtype=torch.bool)
        for b, it in enumerate(items):
            n = it["q_vl"].shape[0]
            q_vl[b, :n] = it["q_vl"].float()
            mask[b, :n] = True
        batch["q_vl"], batch["q_vl_mask"] = q_vl, mask
    for key in ("dynamics_static", "dynamics_wrist", "subgoal_position"):
        if key in items[0]:
            batch[key] = torch.stack([it[key] for it in items]).float()
    if "subgoal_in_loss" in items[0]:
        batch["subgoal_in_loss"] = torch.stack([it["subgoal_in_loss"] for it in items])
    return batch
