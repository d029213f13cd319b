"""Training samples from a LeRobot dataset: an observation history, a future video clip (for
System 3's video objective) and an action chunk, for every frame of every episode.

Sample for frame t of an episode with T frames (keys; shapes with the defaults):

    instruction             str, the episode's task text; task_index int
    observation.state       (history, 18) float32, frames t-history+1 .. t
    observation.images.<k>  (history, H, W, 3) uint8 for each camera k
    observation_is_pad      (history,) bool, True where t-i < 0 (the first frame is repeated there)
    future.images.<k>       (future_frames, H, W, 3) uint8, frames t+s, t+2s, ... (s = future_stride)
    future_is_pad           (future_frames,) bool, True past the episode's end (last frame repeated)
    action                  (chunk_size, 7) float32, actions t .. t+chunk_size-1
    action_is_pad           (chunk_size,) bool, True past the end, where the action is a hold
                            (zero motion, the last gripper command)
    action_is_stale         (chunk_size,) bool, True where a disturbed step (collection with action
                            noise, episode metadata 'trivla/perturbed_frames') lies between frame t and
                            that action: it answers a state frame t does not show, so it is no label
    subgoal_position        (3,) float32 [m], where the tool-centre point is when the gripper next
                            changes (data/subgoals.py); only when the dataset has observation.tcp_pose
    subgoal_in_loss         bool, frame t trains the instruction grounding: it lies before the episode's
                            first gripper change, or carries the block of a `grounding_carry_tasks` task
    episode_index, frame_index

Decoded videos of the most recently used episodes are cached (`cache_episodes`).
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from trivla_drake.data.lerobot_format import EPISODE_TASK_KEY, PERTURBED_FRAMES_KEY
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.subgoals import (
    approach_frames,
    carry_frames,
    next_gripper_event_positions,
)

GRIPPER_INDEX = 6
TCP_POSE_KEY = "observation.tcp_pose"  # (7,): x, y, z [m] in the world, then a quaternion


class TrainingSamples:
    """Indexable dataset of training samples (works as a torch Dataset: __len__ and __getitem__)."""

    def __init__(
        self,
        reader: LeRobotReader | str,
        *,
        history: int = 2,
        future_frames: int = 8,
        future_stride: int = 3,
        chunk_size: int = 10,
        cameras: list[str] | None = None,
        state_key: str = "observation.state",
        action_key: str = "action",
        cache_episodes: int = 4,
        grounding_carry_tasks: tuple[str, ...] = (),
    ):
        self.reader = reader if isinstance(reader, LeRobotReader) else LeRobotReader(reader)
        for name, value in (("history", history), ("chunk_size", chunk_size), ("future_stride", future_stride)):
            if value < 1:
                raise ValueError(f"{name} must be at least 1, got {value}")
        if future_frames < 0:
            raise ValueError(f"future_frames must be >= 0, got {future_frames}")
        self.history, self.future_frames, self.future_stride = history, future_frames, future_stride
        self.chunk_size = chunk_size
        self.cameras = list(self.reader.camera_keys if cameras is None else cameras)
        unknown = [c for c in self.cameras if c not in self.reader.camera_keys]
        if unknown:
            raise ValueError(f"unknown cameras {unknown}; the dataset has {self.reader.camera_keys}")
        for key in (state_key, action_key):
            if key not in self.reader.features:
                raise ValueError(f"the dataset has no feature {key!r}; it has {sorted(self.reader.features)}")
        self.state_key, self.action_key = state_key, action_key
        lengths = np.array([e["length"] for e in self.reader.episodes], dtype=np.int64)
        self._starts = np.concatenate([[0], np.cumsum(lengths)])
        self._cache: OrderedDict[int, dict] = OrderedDict()
        self._cache_size = max(1, cache_episodes)
        # Episodes of these tasks (their recorded `trivla/task`) also train the grounding on their carrying
        # frames (data/subgoals.py, `carry_frames`).
        self.grounding_carry_tasks = frozenset(grounding_carry_tasks)

    def __len__(self) -> int:
        return int(self._starts[-1])

    def locate(self, index: int) -> tuple[int, int]:
        """(episode, frame) of a global sample index."""
        if not 0 <= index < len(self):
            raise IndexError(f"sample index {index} out of range [0, {len(self)})")
        episode = int(np.searchsorted(self._starts, index, side="right") - 1)
        return episode, int(index - self._starts[episode])

    def grounding_frames(self, episode: int) -> np.ndarray:
        """bool (T,) of one episode: the frames that train the instruction grounding: those before its first
        gripper change (data/subgoals.py), and for a task in `grounding_carry_tasks` its carrying frames.
        Needs the dataset's observation.tcp_pose."""
        data = self._episode(episode)
        if "subgoal_in_loss" not in data:
            raise ValueError(f"the dataset at {self.reader.root} has no {TCP_POSE_KEY!r}: it has no sub-goal labels")
        return np.asarray(data["subgoal_in_loss"], dtype=bool)

    def gripper_commands(self, episode: int) -> np.ndarray:
        """float (T,): one episode's recorded gripper commands (+1 open, -1 closed)."""
        return np.asarray(self._episode(episode)[self.action_key])[:, GRIPPER_INDEX]

    def _episode(self, episode: int) -> dict:
        if episode in self._cache:
            self._cache.move_to_end(episode)
            return self._cache[episode]
        data = self.reader.episode_frames(episode)
        data["videos"] = {key: self.reader.episode_video(episode, key) for key in self.cameras}
        data["perturbed_before"] = perturbed_counts(
            self.reader.episodes[episode].get(PERTURBED_FRAMES_KEY) or [], len(data[self.action_key])
        )
        if TCP_POSE_KEY in data:
            gripper = np.asarray(data[self.action_key])[:, GRIPPER_INDEX]
            tcp_pose = np.asarray(data[TCP_POSE_KEY])
            data["subgoal_position"] = next_gripper_event_positions(gripper, tcp_pose[:, :3])
            data["subgoal_in_loss"] = approach_frames(gripper)
            if self.reader.episodes[episode].get(EPISODE_TASK_KEY) in self.grounding_carry_tasks:
                data["subgoal_in_loss"] |= carry_frames(gripper)
        self._cache[episode] = data
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return data

    def __getitem__(self, index: int) -> dict:
        episode, t = self.locate(int(index))
        data = self._episode(episode)
        length = len(data[self.action_key])
        past = t - np.arange(self.history - 1, -1, -1)
        future = t + self.future_stride * np.arange(1, self.future_frames + 1)
        chunk = t + np.arange(self.chunk_size)
        actions = np.asarray(data[self.action_key], dtype=np.float32)[np.minimum(chunk, length - 1)].copy()
        action_pad = chunk >= length
        if action_pad.any():
            # Past the end the robot holds: no motion, the last gripper command.
            actions[action_pad, :GRIPPER_INDEX] = 0.0
        # Disturbed steps in t .. t+k-1 for chunk entry k (entry 0 is the expert's answer to frame t).
        before = data["perturbed_before"]
        stale = before[np.minimum(chunk, length)] > before[t]
        sample = {
            "instruction": self.reader.task_of(episode),
            "task_index": int(data["task_index"][t]),
            "episode_index": episode,
            "frame_index": t,
            self.state_key: np.asarray(data[self.state_key], dtype=np.float32)[np.maximum(past, 0)],
            "observation_is_pad": past < 0,
            self.action_key: actions,
            "action_is_pad": action_pad,
            "action_is_stale": stale,
            "future_is_pad": future >= length,
        }
        if "subgoal_position" in data:
            sample["subgoal_position"] = data["subgoal_position"][t]
            sample["subgoal_in_loss"] = bool(data["subgoal_in_loss"][t])
        for key in self.cameras:
            frames = data["videos"][key]
            n = len(frames)
            sample[key] = frames[np.clip(past, 0, n - 1)]
            sample[key.replace("observation.", "future.", 1)] = frames[np.clip(future, 0, n - 1)]
        return sample


def perturbed_counts(frames, length: int) -> np.ndarray:
    """(length + 1,) int: entry i counts the disturbed steps among frames 0 .. i-1."""
    flags = np.zeros(length, dtype=np.int64)
    frames = np.asarray(frames, dtype=np.int64)
    if frames.size and (frames.min() < 0 or frames.max() >= length):
        raise ValueError(f"perturbed frame indices must lie in [0, {length}), got {frames.min()}..{frames.max()}")
    flags[frames] = 1
    return np.concatenate([[0], np.cumsum(flags)])
