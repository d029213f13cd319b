"""The three video codecs (data/video.py): each written and read back; the dataset writer records what its files
are and keeps one codec per dataset; `CollectConfig.video_codec` names itself in every refusal."""

import json

import numpy as np
import pytest

from trivla_drake.data import video
from trivla_drake.data.lerobot_format import dataset_video_codec, vector_feature, video_feature
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.data.video import VIDEO_CODECS, probe_video, read_video, write_video
from trivla_drake.eval.collect_config import CollectConfig

FPS = 36.0
CAMERA = "observation.images.static"
FEATURES = {CAMERA: video_feature(16, 16, FPS), "observation.state": vector_feature(["s0", "s1"])}


def _frames(length: int, size: int = 16) -> np.ndarray:
    """Flat frames whose brightness steps with the frame index (lossy codecs keep flat colours)."""
    frames = np.empty((length, size, size, 3), np.uint8)
    frames[:] = (40 + 20 * np.arange(length, dtype=np.uint8))[:, None, None, None]
    frames[..., 1] //= 2
    return frames


def _episode(length: int = 6) -> dict:
    return {"observation.state": np.arange(2 * length, dtype=np.float32).reshape(length, 2)}


@pytest.mark.parametrize("codec", VIDEO_CODECS)
def test_each_codec_writes_and_reads_back(tmp_path, codec):
    frames = _frames(8)
    path = write_video(tmp_path / f"{codec}.mp4", frames, FPS, codec)
    probe = probe_video(path)
    assert (probe["codec"], probe["pix_fmt"], probe["height"], probe["width"]) == (codec, "yuv420p", 16, 16)
    decoded = read_video(path)
    assert decoded.shape == frames.shape and decoded.dtype == np.uint8
    error = np.abs(decoded.astype(int) - frames.astype(int)).mean(axis=(1, 2, 3))
    assert error.max() < 4, error  # every frame in its place (neighbours differ by 20 levels)
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary file was renamed


def test_bad_codec_and_frames_are_named(tmp_path):
    with pytest.raises(ValueError, match=r"codec must be one of \['mpeg4', 'h264', 'av1'\], got 'vp9'"):
        write_video(tmp_path / "a.mp4", _frames(2), FPS, "vp9")
    with pytest.raises(ValueError, match="even frame size, got 15x15"):
        write_video(tmp_path / "b.mp4", _frames(2, size=15), FPS, "h264")
    assert not list(tmp_path.iterdir())  # nothing left behind


def test_a_codec_without_an_encoder_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(video._ENCODERS, "av1", ["no-such-encoder"])
    with pytest.raises(ValueError, match=r"video_codec 'av1'.*none of the encoders \['no-such-encoder'\].*'mpeg4'"):
        video.video_encoder("av1", "video_codec")


def test_info_json_says_what_the_files_are(tmp_path):
    """The features declare mpeg4 (as `collect` builds them); the first episode's files are AV1: info.json
    follows the files, and a resumed writer encodes frames in the dataset's codec."""
    root = tmp_path / "ds"
    staged = write_video(tmp_path / "staged.mp4", _frames(6), FPS, "av1")
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES)
    writer.add_episode(_episode(), "task", videos={CAMERA: str(staged)})
    info = json.loads((root / "meta/info.json").read_text())["features"][CAMERA]["info"]
    assert (info["video.codec"], info["video.pix_fmt"], info["video.fps"]) == ("av1", "yuv420p", 36)
    assert dataset_video_codec(root) == "av1"
    resumed = LeRobotWriter(root, fps=FPS, features=FEATURES)
    assert resumed.video_codec == "av1"
    resumed.add_episode(_episode(), "task", videos={CAMERA: _frames(6)})
    reader = LeRobotReader(root)
    assert probe_video(root / reader.episode_files(1)[1])["codec"] == "av1"
    assert reader.episode_video(1, CAMERA).shape == (6, 16, 16, 3)


def test_one_dataset_holds_one_codec(tmp_path):
    root = tmp_path / "ds"
    LeRobotWriter(root, fps=FPS, features=FEATURES).add_episode(_episode(), "task", videos={CAMERA: _frames(6)})
    assert dataset_video_codec(root) == "mpeg4"
    with pytest.raises(ValueError, match=r"video_codec 'h264': .* holds 1 episodes of 'mpeg4' video"):
        LeRobotWriter(root, fps=FPS, features=FEATURES, video_codec="h264")
    other = write_video(tmp_path / "other.mp4", _frames(6), FPS, "h264")
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES)
    with pytest.raises(ValueError, match=r"video_codec: .* is 'h264' but .* holds 'mpeg4' video"):
        writer.add_episode(_episode(), "task", videos={CAMERA: str(other)})
    assert LeRobotReader(root).num_episodes == 1 and other.exists()  # nothing written, the file left in place
    with pytest.raises(ValueError, match="has 6 frames, the episode 4"):
        writer.add_episode(_episode(4), "task", videos={CAMERA: str(write_video(other, _frames(6), FPS))})


def test_collect_config_names_video_codec(tmp_path):
    with pytest.raises(ValueError, match=r"video_codec must be one of \['mpeg4', 'h264', 'av1'\], got 'vp9'"):
        CollectConfig(out=str(tmp_path / "new"), video_codec="vp9").validate()
    root = tmp_path / "ds"
    LeRobotWriter(root, fps=FPS, features=FEATURES).add_episode(_episode(), "task", videos={CAMERA: _frames(6)})
    with pytest.raises(ValueError, match=r"video_codec 'av1': .* holds 'mpeg4' video.*--set video_codec=mpeg4"):
        CollectConfig(out=str(root), video_codec="av1").validate()
    assert CollectConfig().video_codec == "mpeg4"
