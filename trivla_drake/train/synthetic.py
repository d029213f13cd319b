"""A small synthetic LeRobot dataset with the collector's features (Panda state, 7-D end-effector
actions, static and wrist cameras), for tests, examples and timing runs without the simulator.

Each episode shows a coloured square moving across a plain background (so clips have motion); the
state follows smooth curves and the action is the state's next change plus a gripper command, so a
policy has something learnable.
"""

from __future__ import annotations

import os

import numpy as np

from trivla_drake.data.lerobot_format import EPISODE_TASK_KEY, vector_feature, video_feature
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.nn.config import EE_DELTA_ACTION_NAMES, PANDA_STATE_NAMES

CAMERAS = ("observation.images.static", "observation.images.wrist")
TASKS = ("lift the red block", "open the drawer", "switch the lamp on")


TCP_POSE_NAMES = ("x", "y", "z", "qw", "qx", "qy", "qz")


def synthetic_features(image_size: int, fps: float, tcp_pose: bool = False) -> dict[str, dict]:
    """info.json features of the synthetic dataset (the collector's; the tcp pose only with `tcp_pose`)."""
    features = {
        CAMERAS[0]: video_feature(image_size, image_size, fps),
        CAMERAS[1]: video_feature(image_size, image_size, fps),
        "observation.state": vector_feature(list(PANDA_STATE_NAMES)),
        "action": vector_feature(list(EE_DELTA_ACTION_NAMES)),
    }
    if tcp_pose:
        features["observation.tcp_pose"] = vector_feature(list(TCP_POSE_NAMES))
    return features


def _frames(length: int, size: int, rng: np.random.Generator, color: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames (T, size, size, 3) of a square moving in a straight line, and its corner (T, 2) [pixels]."""
    frames = np.empty((length, size, size, 3), dtype=np.uint8)
    frames[:] = rng.integers(40, 90, size=3, dtype=np.uint8)
    side = max(2, size // 4)
    start, end = rng.uniform(0, size - side, size=2), rng.uniform(0, size - side, size=2)
    corners = np.empty((length, 2), dtype=np.int64)
    for t in range(length):
        x, y = corners[t] = (start + (end - start) * t / max(1, length - 1)).astype(int)
        frames[t, y : y + side, x : x + side] = color
    return frames, corners


def write_synthetic_dataset(
    root: str | os.PathLike,
    *,
    episodes: int = 3,
    length: int = 24,
    image_size: int = 32,
    fps: float = 36.0,
    seed: int = 0,
    lengths: list[int] | None = None,
    phrasings: int = 1,
    tcp_pose: bool = False,
) -> str:
    """Writes `episodes` episodes (of `length` frames, or `lengths`) to `root`; returns the path.
    Episode i demonstrates task i % 3; with `phrasings` > 1 its instruction is one of that many
    phrasings of the task and the task's name is recorded per episode, as `collect` does. With
    `tcp_pose`, observation.tcp_pose follows the static view's square (x, y = its corner / size [m])."""
    if os.path.exists(os.path.join(root, "meta", "info.json")):
        raise ValueError(f"{root} already holds a dataset; write the synthetic one elsewhere")
    rng = np.random.default_rng(seed)
    writer = LeRobotWriter(root, fps=fps, features=synthetic_features(image_size, fps, tcp_pose))
    lengths = list(lengths) if lengths is not None else [length] * episodes
    for i, n in enumerate(lengths):
        color = np.array([[255, 40, 40], [40, 200, 40], [40, 40, 255]][i % 3], dtype=np.uint8)
        t = np.arange(n + 1)[:, None] / fps
        phase = rng.uniform(0, 2 * np.pi, size=(1, 9))
        q = 0.3 * np.sin(t * 2.0 + phase)  # 9 positions
        v = np.gradient(q, axis=0) * fps
        state = np.concatenate([q, v], axis=1)[:n].astype(np.float32)
        action = np.zeros((n, 7), dtype=np.float32)
        action[:, :6] = 0.01 * np.diff(q[:, :6], axis=0) * fps
        action[:, 6] = np.where(np.arange(n) < n // 2, 1.0, -1.0)
        (static, corners), (wrist, _) = _frames(n, image_size, rng, color), _frames(n, image_size, rng, 255 - color)
        videos = {CAMERAS[0]: static, CAMERAS[1]: wrist}
        columns = {"observation.state": state, "action": action}
        if tcp_pose:
            pose = np.zeros((n, 7), dtype=np.float32)
            pose[:, :2], pose[:, 2], pose[:, 3] = corners / image_size, 0.1, 1.0
            columns["observation.tcp_pose"] = pose
        task = TASKS[i % len(TASKS)]
        instruction = task if phrasings == 1 else f"{task} (phrasing {(i // len(TASKS)) % phrasings})"
        writer.add_episode(columns, instruction, videos=videos,
                           extra={EPISODE_TASK_KEY: task} if phrasings > 1 else None)
    return str(root)
