"""MP4 files from RGB frames and back, in one of three codecs (`VIDEO_CODECS`, by the names ffmpeg and lerobot's
info.json give them):

- "mpeg4": MPEG-4 Part 2 (fourcc 'mp4v'), written and read with OpenCV, as every dataset before the other two was;
- "h264": H.264 (libx264), written and read with PyAV;
- "av1": AV1 (libsvtav1, else libaom-av1), written and read with PyAV; lerobot v3's default codec.

PyAV writes yuv420p with a keyframe every `KEYFRAME_INTERVAL` frames (lerobot's setting: a frame is decoded from at
most one frame before it when a reader seeks) at quality `CRF` (lower: better and larger).
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from trivla_drake.data.durable import fsync_file

VIDEO_CODEC = "mpeg4"  # the default: the name ffmpeg (and lerobot's info.json) use for the fourcc 'mp4v'
VIDEO_CODECS = ["mpeg4", "h264", "av1"]
PIX_FMT = "yuv420p"
_FOURCC = "mp4v"
# PyAV encoders of each codec, in order of preference.
_ENCODERS = {"h264": ["libx264"], "av1": ["libsvtav1", "libaom-av1"]}
KEYFRAME_INTERVAL = 2
CRF = {"h264": 23, "av1": 30}
_ENCODER_OPTIONS = {  # beyond the keyframe interval and the crf
    "libx264": {"preset": "medium"},
    "libsvtav1": {"preset": "8"},
    "libaom-av1": {"cpu-used": "8", "row-mt": "1"},
}


def video_encoder(codec: str, field: str = "video_codec") -> str | None:
    """The encoder that writes `codec` (None: OpenCV's, for "mpeg4"). ValueError naming `field` for a codec not
    in VIDEO_CODECS, or one no installed PyAV encoder writes."""
    if codec not in VIDEO_CODECS:
        raise ValueError(f"{field} must be one of {VIDEO_CODECS}, got {codec!r}")
    if codec == "mpeg4":
        return None
    try:
        import av
    except ImportError as error:
        raise ValueError(f"{field} {codec!r} needs PyAV (pip install av): {error}") from None
    for name in _ENCODERS[codec]:
        try:
            av.codec.Codec(name, "w")
            return name
        except Exception:  # noqa: BLE001 - PyAV's UnknownCodecError and friends: this build lacks it
            continue
    raise ValueError(f"{field} {codec!r}: this PyAV build ({av.__version__}) has none of the encoders "
                     f"{_ENCODERS[codec]}; install a PyAV wheel that ships one, or use {field} 'mpeg4'")


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float, codec: str = VIDEO_CODEC) -> Path:
    """Write (T, H, W, 3) uint8 RGB frames to `path` as mp4 in `codec` (one of VIDEO_CODECS), atomically (a
    temporary file renamed)."""
    encoder = video_encoder(codec, "codec")
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise ValueError(f"frames must be a non-empty uint8 array (T, H, W, 3), got {frames.dtype} {frames.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.mp4")
    try:
        if encoder is None:
            _write_opencv(tmp, frames, fps)
        else:
            _write_pyav(tmp, frames, fps, codec, encoder)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_file(tmp)
    os.replace(tmp, path)
    return path


def _write_opencv(path: Path, frames: np.ndarray, fps: float) -> None:
    import cv2

    height, width = frames.shape[1:3]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*_FOURCC), float(fps), (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot open an mp4 writer for {path}")
    try:
        for frame in frames:
            writer.write(np.ascontiguousarray(frame[:, :, ::-1]))  # OpenCV wants BGR
    finally:
        writer.release()


def _write_pyav(path: Path, frames: np.ndarray, fps: float, codec: str, encoder: str) -> None:
    import av

    height, width = frames.shape[1:3]
    if height % 2 or width % 2:
        raise ValueError(f"{codec} video ({PIX_FMT}) needs an even frame size, got {width}x{height}")
    options = {"g": str(KEYFRAME_INTERVAL), "crf": str(CRF[codec]), **_ENCODER_OPTIONS[encoder]}
    if encoder == "libsvtav1":
        os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its settings to stderr for every file: errors only
    rate = Fraction(fps).limit_denominator(1001)
    with av.open(str(path), "w", format="mp4") as container:
        stream = container.add_stream(encoder, rate=rate, options=options)
        stream.width, stream.height, stream.pix_fmt = width, height, PIX_FMT
        for frame in frames:
            image = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            container.mux(stream.encode(image))
        container.mux(stream.encode())  # flush the encoder


def probe_video(path: str | os.PathLike) -> dict:
    """What a video file holds, as lerobot's info.json names it: codec (ffmpeg's name), pix_fmt, height, width,
    and frames (the count the container records, 0 when it records none)."""
    import av

    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            return {"codec": stream.codec_context.codec.canonical_name, "pix_fmt": stream.codec_context.pix_fmt,
                    "height": stream.codec_context.height, "width": stream.codec_context.width,
                    "frames": int(stream.frames)}
    except (av.FFmpegError, IndexError) as error:
        raise ValueError(f"cannot read video {path}: {error}") from error


def read_video(path: str | os.PathLike) -> np.ndarray:
    """All frames of a video as (T, H, W, 3) uint8 RGB: an "mpeg4" one decoded with OpenCV (as always), an "h264"
    or "av1" one with PyAV."""
    if probe_video(path)["codec"] == "mpeg4":
        frames = _read_opencv(path)
    else:
        frames = _read_pyav(path)
    if not frames:
        raise ValueError(f"video {path} has no readable frames")
    return np.ascontiguousarray(np.stack(frames))


def _read_opencv(path: str | os.PathLike) -> list[np.ndarray]:
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
    return frames


def _read_pyav(path: str | os.PathLike) -> list[np.ndarray]:
    import av

    try:
        with av.open(str(path)) as container:
            return [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    except av.FFmpegError as error:
        raise ValueError(f"cannot decode video {path}: {error}") from error
