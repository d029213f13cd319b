"""MP4 files from RGB frames and back, with OpenCV (codec MPEG-4 part 2, 'mp4v': the one the
opencv-python wheels can encode; ffmpeg, PyAV and torchcodec all decode it)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from trivla_drake.data.durable import fsync_file

VIDEO_CODEC = "mpeg4"  # the name ffmpeg (and lerobot's info.json) use for the fourcc 'mp4v'
_FOURCC = "mp4v"


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float) -> Path:
    """Write (T, H, W, 3) uint8 RGB frames to `path` as mp4, atomically (a temporary file renamed)."""
    import cv2

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise ValueError(f"frames must be a non-empty uint8 array (T, H, W, 3), got {frames.dtype} {frames.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.mp4")
    height, width = frames.shape[1:3]
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*_FOURCC), float(fps), (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot open an mp4 writer for {path}")
    try:
        for frame in frames:
            writer.write(np.ascontiguousarray(frame[:, :, ::-1]))  # OpenCV wants BGR
    finally:
        writer.release()
    fsync_file(tmp)
    os.replace(tmp, path)
    return path


def read_video(path: str | os.PathLike) -> np.ndarray:
    """All frames of a video as (T, H, W, 3) uint8 RGB."""
    import cv2

    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise ValueError(f"cannot open video {path}")
    frames = []
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            frames.append(frame[:, :, ::-1])
    finally:
        capture.release()
    if not frames:
        raise ValueError(f"video {path} has no readable frames")
    return np.ascontiguousarray(np.stack(frames))
