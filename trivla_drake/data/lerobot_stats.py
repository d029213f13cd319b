"""Per-feature statistics of a LeRobot dataset (meta/stats.json and each episode's stats/* columns), as lerobot
computes them: min / max / mean / std / count."""

from __future__ import annotations

import numpy as np


def array_stats(values: np.ndarray) -> dict[str, list]:
    """min / max / mean / std / count over the first axis of (N, D) values."""
    values = np.asarray(values, dtype=np.float64)
    return {
        "min": values.min(0).tolist(),
        "max": values.max(0).tolist(),
        "mean": values.mean(0).tolist(),
        "std": values.std(0).tolist(),
        "count": [int(values.shape[0])],
    }


def image_stats(frames: np.ndarray, *, frame_stride: int = 5, pixel_stride: int = 4) -> dict[str, list]:
    """Per-channel statistics of uint8 (T, H, W, 3) frames scaled to [0, 1], shaped (3, 1, 1) as
    lerobot stores them; computed on every `frame_stride`-th frame and pixel grid point."""
    sample = np.asarray(frames)[::frame_stride, ::pixel_stride, ::pixel_stride].reshape(-1, 3) / 255.0
    stats = array_stats(sample)
    shaped = {k: [[[v]] for v in stats[k]] for k in ("min", "max", "mean", "std")}
    shaped["count"] = [int(len(frames[::frame_stride]))]
    return shaped


def aggregate_stats(per_episode: list[dict[str, dict]]) -> dict[str, dict]:
    """Combine per-episode statistics (weighted by their counts) into dataset statistics."""
    out: dict[str, dict] = {}
    keys = sorted({k for stats in per_episode for k in stats})
    for key in keys:
        parts = [s[key] for s in per_episode if key in s]
        counts = np.array([p["count"][0] for p in parts], dtype=np.float64)
        means = np.stack([np.asarray(p["mean"], dtype=np.float64) for p in parts])
        stds = np.stack([np.asarray(p["std"], dtype=np.float64) for p in parts])
        shape = (-1,) + (1,) * (means.ndim - 1)
        weights = (counts / counts.sum()).reshape(shape)
        mean = (weights * means).sum(0)
        var = (weights * (stds**2 + (means - mean) ** 2)).sum(0)
        out[key] = {
            "min": np.min(np.stack([np.asarray(p["min"]) for p in parts]), 0).tolist(),
            "max": np.max(np.stack([np.asarray(p["max"]) for p in parts]), 0).tolist(),
            "mean": mean.tolist(),
            "std": np.sqrt(np.maximum(var, 0.0)).tolist(),
            "count": [int(counts.sum())],
        }
    return out


def episode_stats(row: dict) -> dict[str, dict]:
    """One episode's statistics ({feature: {metric: value}}) from its meta/episodes row."""
    stats: dict[str, dict] = {}
    for column, value in row.items():
        if column.startswith("stats/") and value is not None:
            _, rest = column.split("/", 1)
            feature, metric = rest.rsplit("/", 1)
            stats.setdefault(feature, {})[metric] = value
    return stats
