"""Every field lerobot 0.4's `LeRobotDatasetMetadata` / `LeRobotDataset` read from a v3.0 folder, in the type it
reads it as, checked on a folder our writer makes (synthetic frames, one dataset per video codec).

What lerobot reads (src/lerobot/datasets/lerobot_dataset.py and utils.py, v0.4.4): info.json (codebase_version
parsed as a version, fps used as an int, features' dtype / shape / names, the video info block, totals, chunks_size,
the file-size limits, data_path / video_path formatted with chunk_index, file_index and video_key, splits,
robot_type); meta/tasks.parquet through pandas (the task text is the index, task_index a column); every
meta/episodes file through Hugging Face datasets (one schema across files), its non-stats columns; the data
parquet files against features built from info.json (a vector is a fixed-length list, a [1] feature a scalar);
meta/stats.json with min / max / mean / std / count and the quantiles, images (3, 1, 1) and count (1,).
research/lerobot_check/ opens a collected folder with lerobot itself.
"""

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from trivla_drake.data.lerobot_format import vector_feature, video_feature
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.data.video import VIDEO_CODECS, probe_video

FPS = 36.0
SIZE = 16
CAMERAS = ["observation.images.static", "observation.images.wrist"]
VECTORS = {"observation.state": 4, "observation.tcp_pose": 7, "action": 7}
INDEX_COLUMNS = {"timestamp": pa.float32(), "frame_index": pa.int64(), "episode_index": pa.int64(),
                 "index": pa.int64(), "task_index": pa.int64()}
METRICS = {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}
EPISODES = [(6, "lift the block"), (9, "open the drawer"), (5, "lift the block")]


@pytest.fixture(scope="module", params=VIDEO_CODECS)
def dataset(request, tmp_path_factory):
    root = tmp_path_factory.mktemp(f"schema_{request.param}") / "ds"
    features = {**{camera: video_feature(SIZE, SIZE, FPS) for camera in CAMERAS},
                **{key: vector_feature([f"{key}_{i}" for i in range(dim)]) for key, dim in VECTORS.items()}}
    writer = LeRobotWriter(root, fps=FPS, features=features, video_codec=request.param)
    rng = np.random.default_rng(0)
    for length, task in EPISODES:
        frames = {key: rng.normal(size=(length, dim)).astype(np.float32) for key, dim in VECTORS.items()}
        videos = {camera: rng.integers(0, 256, size=(length, SIZE, SIZE, 3), dtype=np.uint8) for camera in CAMERAS}
        writer.add_episode(frames, task, videos=videos)
    return root, request.param


def _info(root):
    return json.loads((root / "meta/info.json").read_text())


def _episode_rows(root):
    tables = [pq.read_table(p) for p in sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))]
    assert len({t.schema for t in tables}) == 1, "every meta/episodes file must have one schema"
    return pa.concat_tables(tables)


def test_info_json(dataset):
    root, codec = dataset
    info = _info(root)
    assert info["codebase_version"] == "v3.0"
    assert type(info["fps"]) is int and info["fps"] == 36
    assert info["robot_type"] == "panda"
    totals = {"total_episodes": len(EPISODES), "total_frames": sum(n for n, _ in EPISODES), "total_tasks": 2}
    for key, value in {**totals, "chunks_size": 1000}.items():
        assert type(info[key]) is int and info[key] == value, key
    assert type(info["data_files_size_in_mb"]) is int and type(info["video_files_size_in_mb"]) is int
    assert info["splits"] == {"train": f"0:{len(EPISODES)}"}
    assert info["data_path"].format(chunk_index=0, file_index=2) == "data/chunk-000/file-002.parquet"
    assert info["video_path"].format(video_key=CAMERAS[0], chunk_index=1, file_index=3) == \
        f"videos/{CAMERAS[0]}/chunk-001/file-003.mp4"
    assert set(info["features"]) == set(CAMERAS) | set(VECTORS) | set(INDEX_COLUMNS)
    for name, feature in info["features"].items():
        assert {"dtype", "shape", "names"} <= set(feature), name
        assert all(type(n) is int and n > 0 for n in feature["shape"]), name
        if name in INDEX_COLUMNS:
            assert feature["shape"] == [1] and feature["dtype"] == ("float32" if name == "timestamp" else "int64")
        elif name in VECTORS:
            assert feature["dtype"] == "float32" and feature["shape"] == [VECTORS[name]]
            assert len(feature["names"]) == VECTORS[name]


def test_video_info_block_says_what_the_files_are(dataset):
    root, codec = dataset
    info = _info(root)
    for camera in CAMERAS:
        feature = info["features"][camera]
        assert feature["dtype"] == "video" and feature["shape"] == [SIZE, SIZE, 3]
        assert feature["names"] == ["height", "width", "channels"]
        block = feature["info"]
        assert block == {"video.height": SIZE, "video.width": SIZE, "video.codec": codec, "video.pix_fmt": "yuv420p",
                         "video.is_depth_map": False, "video.fps": 36, "video.channels": 3, "has_audio": False}
        assert type(block["video.fps"]) is int
        for episode in range(len(EPISODES)):
            path = root / info["video_path"].format(video_key=camera, chunk_index=0, file_index=episode)
            probe = probe_video(path)
            assert (probe["codec"], probe["pix_fmt"], probe["frames"]) == (codec, "yuv420p", EPISODES[episode][0])


def test_tasks_parquet(dataset):
    root, _ = dataset
    table = pq.read_table(root / "meta/tasks.parquet")
    assert table.schema.field("task_index").type == pa.int64() and table.schema.field("task").type == pa.string()
    assert table.column("task").to_pylist() == ["lift the block", "open the drawer"]
    assert table.column("task_index").to_pylist() == [0, 1]
    pandas = json.loads(table.schema.metadata[b"pandas"])
    assert pandas["index_columns"] == ["task"]  # lerobot looks a task up by its text: the index


def test_episodes_parquet(dataset):
    root, _ = dataset
    table = _episode_rows(root)
    schema = table.schema
    int_columns = ["episode_index", "length", "data/chunk_index", "data/file_index", "dataset_from_index",
                   "dataset_to_index", "meta/episodes/chunk_index", "meta/episodes/file_index"]
    for camera in CAMERAS:
        int_columns += [f"videos/{camera}/chunk_index", f"videos/{camera}/file_index"]
        for column in (f"videos/{camera}/from_timestamp", f"videos/{camera}/to_timestamp"):
            assert pa.types.is_floating(schema.field(column).type), column
    for column in int_columns:
        assert schema.field(column).type == pa.int64(), column
    assert schema.field("tasks").type == pa.list_(pa.string())
    rows = table.to_pylist()
    start = 0
    for i, (row, (length, task)) in enumerate(zip(rows, EPISODES)):
        assert (row["episode_index"], row["length"], row["tasks"]) == (i, length, [task])
        assert (row["dataset_from_index"], row["dataset_to_index"]) == (start, start + length)
        for camera in CAMERAS:  # an episode's frames are [from_timestamp, to_timestamp) of its video
            assert row[f"videos/{camera}/from_timestamp"] == 0.0
            assert row[f"videos/{camera}/to_timestamp"] == pytest.approx(length / FPS)
        start += length
    stats_columns = {name for name in schema.names if name.startswith("stats/")}
    features = set(CAMERAS) | set(VECTORS) | set(INDEX_COLUMNS)
    assert stats_columns == {f"stats/{f}/{m}" for f in features for m in METRICS}


def test_data_parquet(dataset):
    root, _ = dataset
    info = _info(root)
    for row in _episode_rows(root).to_pylist():
        path = root / info["data_path"].format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])
        table = pq.read_table(path)
        assert set(table.column_names) == set(VECTORS) | set(INDEX_COLUMNS)
        for name, kind in INDEX_COLUMNS.items():
            assert table.schema.field(name).type == kind, name
        for name, dim in VECTORS.items():  # lerobot's Sequence(length=D, float32): a fixed-size list
            assert table.schema.field(name).type == pa.list_(pa.float32(), dim), name
        length = row["length"]
        frame_index = table.column("frame_index").to_numpy()
        assert frame_index.tolist() == list(range(length))
        assert table.column("index").to_numpy().tolist() == list(range(row["dataset_from_index"],
                                                                       row["dataset_to_index"]))
        assert set(table.column("episode_index").to_pylist()) == {row["episode_index"]}
        # lerobot checks timestamps against fps with a 1e-4 s tolerance
        assert np.abs(table.column("timestamp").to_numpy() - frame_index / info["fps"]).max() < 1e-4


def test_stats_json(dataset):
    root, _ = dataset
    stats = json.loads((root / "meta/stats.json").read_text())
    assert set(stats) == set(CAMERAS) | set(VECTORS) | set(INDEX_COLUMNS)
    for feature, metrics in stats.items():
        assert set(metrics) == METRICS, feature
        assert np.shape(metrics["count"]) == (1,)
        shape = (3, 1, 1) if feature in CAMERAS else (VECTORS.get(feature, 1),)
        for metric, value in metrics.items():
            if metric != "count":
                assert np.shape(value) == shape, (feature, metric)
        assert np.all(np.asarray(metrics["min"]) <= np.asarray(metrics["q01"]))
        assert np.all(np.asarray(metrics["q99"]) <= np.asarray(metrics["max"]))


def test_fps_must_be_a_whole_number(tmp_path):
    with pytest.raises(ValueError, match="fps must be a positive whole number .* got 12.5"):
        LeRobotWriter(tmp_path / "ds", fps=12.5, features={"observation.state": vector_feature(["s"])})
    assert not (tmp_path / "ds").exists()
