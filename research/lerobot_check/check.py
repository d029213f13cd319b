"""Does a folder written by `trivla-drake collect` open with LeRobot's own `LeRobotDataset`, and does it hold the
frames ours reads? Run in the LeRobot venv of README.md (lerobot 0.4.4 next to this project's CPU torch):

    python research/lerobot_check/check.py /tmp/lr_ds /tmp/lr_ds_av1 --out research/lerobot_check/results.json

For every folder and every frame: state, action, tcp pose, timestamp and the index columns from LeRobot's
`dataset[i]` against `LeRobotReader.episode_frames` (exactly); every camera image LeRobot decodes (torchcodec)
against `LeRobotReader.episode_video` (ours: OpenCV for mpeg4, PyAV for h264 and av1), as the mean and largest
absolute pixel difference; the task text; LeRobot's `aggregate_stats` of our per-episode statistics against our
meta/stats.json; LeRobot's histogram quantiles (`get_feature_stats`) of each episode's columns against ours.
Reaches our package only through `trivla_drake.data.LeRobotReader`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # a local folder: nothing is downloaded
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)


def _import_torchvision_without_its_ops() -> None:
    """torchvision from the registry is a CUDA build whose compiled ops do not load next to a CPU torch; lerobot
    needs only its Python transforms. Its fake-op registrations are skipped while it imports."""
    import torch.library

    real = torch.library.register_fake

    def lenient(op, *args, **kwargs):
        if isinstance(op, str) and op.startswith("torchvision::"):
            return lambda fn: fn
        return real(op, *args, **kwargs)

    torch.library.register_fake = lenient
    try:
        import torchvision  # noqa: F401
    finally:
        torch.library.register_fake = real


_import_torchvision_without_its_ops()

from lerobot.datasets.compute_stats import aggregate_stats, get_feature_stats  # noqa: E402
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402

from trivla_drake.data import LeRobotReader  # noqa: E402

EXACT_COLUMNS = ["observation.state", "action", "observation.tcp_pose", "timestamp", "frame_index",
                 "episode_index", "index", "task_index"]
QUANTILES = ["q01", "q10", "q50", "q90", "q99"]


def _as_numpy(value) -> np.ndarray:
    return value.numpy() if isinstance(value, torch.Tensor) else np.asarray(value)


def check_folder(root: str) -> dict:
    """The comparison figures of one dataset folder (see the module docstring)."""
    ours = LeRobotReader(root)
    theirs = LeRobotDataset(repo_id="trivla/lerobot_check", root=root, video_backend="torchcodec")
    report = {"folder": root, "codec": theirs.meta.features[ours.camera_keys[0]]["info"]["video.codec"],
              "episodes": theirs.num_episodes, "frames": len(theirs), "fps": theirs.fps,
              "mismatched_columns": {}, "image_mean_abs_diff": {}, "image_max_abs_diff": {},
              "control_image_mean_abs_diff_to_next_frame": {}}
    assert theirs.num_episodes == ours.num_episodes and len(theirs) == ours.num_frames
    frames = {e: ours.episode_frames(e) for e in range(ours.num_episodes)}
    videos = {(e, k): ours.episode_video(e, k) for e in range(ours.num_episodes) for k in ours.camera_keys}
    diffs = {k: [] for k in ours.camera_keys}
    controls = {k: [] for k in ours.camera_keys}  # against our next frame: what a one-frame shift would show
    tasks_equal = True
    for i in range(len(theirs)):
        item = theirs[i]
        episode, frame = int(item["episode_index"]), int(item["frame_index"])
        for column in EXACT_COLUMNS:
            mine = np.asarray(frames[episode][column][frame])
            if not np.array_equal(_as_numpy(item[column]).reshape(mine.shape), mine):
                report["mismatched_columns"].setdefault(column, []).append(i)
        tasks_equal &= item["task"] == ours.task_of(episode)
        for key in ours.camera_keys:
            image = np.round(_as_numpy(item[key]).transpose(1, 2, 0) * 255.0).astype(np.int16)
            diffs[key].append(np.abs(image - videos[(episode, key)][frame].astype(np.int16)))
            if frame + 1 < len(videos[(episode, key)]):
                controls[key].append(np.abs(image - videos[(episode, key)][frame + 1].astype(np.int16)).mean())
    for key, parts in diffs.items():
        stacked = np.stack(parts)
        report["image_mean_abs_diff"][key] = float(stacked.mean())
        report["image_max_abs_diff"][key] = int(stacked.max())
        report["control_image_mean_abs_diff_to_next_frame"][key] = float(np.mean(controls[key]))
    report["tasks_equal"] = bool(tasks_equal)
    report.update(_stats_figures(ours, theirs))
    return report


def _stats_figures(ours: LeRobotReader, theirs: LeRobotDataset) -> dict:
    """LeRobot's reading of our statistics: its aggregate of our episodes' against our stats.json, its quantile
    estimate of each episode's columns against ours."""
    per_episode = []
    for row in ours.episodes:  # the stats/<feature>/<metric> columns of meta/episodes, as LeRobot writes them
        stats = {}
        for column, value in row.items():
            if column.startswith("stats/"):
                feature, metric = column[len("stats/"):].rsplit("/", 1)
                stats.setdefault(feature, {})[metric] = np.asarray(value, dtype=np.float64)
        per_episode.append(stats)
    aggregated = aggregate_stats(per_episode)
    stats_json = theirs.meta.stats
    aggregate_gap = max(float(np.max(np.abs(np.asarray(aggregated[f][m]) - np.asarray(stats_json[f][m]))))
                        for f in stats_json for m in stats_json[f] if m != "count")
    quantile_gap = {}
    if f"stats/action/{QUANTILES[0]}" not in ours.episodes[0]:  # written before the quantiles were recorded
        quantile_gap = None
    for column in ("observation.state", "action", "observation.tcp_pose") if quantile_gap is not None else ():
        gaps = []
        for episode in range(ours.num_episodes):
            values = ours.episode_frames(episode)[column].astype(np.float64)
            estimate = get_feature_stats(values, axis=0, keepdims=False)
            span = np.maximum(values.max(0) - values.min(0), 1e-12)
            for q in QUANTILES:
                mine = np.asarray(ours.episodes[episode][f"stats/{column}/{q}"])
                gaps.append(float(np.max(np.abs(estimate[q] - mine) / span)))
        quantile_gap[column] = max(gaps)
    return {"stats_json_metrics": sorted(stats_json[ours.camera_keys[0]]),
            "lerobot_aggregate_vs_stats_json_max_abs_diff": aggregate_gap,
            "lerobot_histogram_quantiles_vs_ours_max_diff_over_range": quantile_gap}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", help="dataset folders written by trivla-drake collect")
    parser.add_argument("--out", help="write the figures here as JSON")
    args = parser.parse_args(argv)
    reports = [check_folder(folder) for folder in args.folders]
    text = json.dumps(reports, indent=2)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    ok = all(not r["mismatched_columns"] and r["tasks_equal"] for r in reports)
    print("every column equal in every frame" if ok else "MISMATCH: see mismatched_columns", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
