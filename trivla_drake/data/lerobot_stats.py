"""Per-feature statistics of a LeRobot dataset (meta/stats.json and each episode's stats/* columns), in lerobot
v3's shape: min / max / mean / std / count and the quantiles q01 / q10 / q50 / q90 / q99 (pi0.5-style policies
normalise by quantiles).

An episode's quantile q is exact: the smallest value with at least a fraction q of the values at or below it
(numpy's "inverted_cdf"), the order statistic lerobot 0.4's 5000-bin histogram estimates (they agree to about one
bin, 1/5000 of the range; an interpolating definition differs by up to a gap between neighbouring values, wide in
the sparse tails of velocities). A dataset's quantiles are the count-weighted mean of its episodes' quantiles, the
rule lerobot 0.4's `aggregate_stats` applies: an approximation (exact when every episode has the same
distribution; between the episodes' values otherwise). A metric some part lacks (episodes written before the
quantiles were recorded) is left out of the aggregate, as lerobot does.
"""

from __future__ import annotations

import numpy as np

# The quantiles lerobot v3 records, by their stats key.
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
BASE_METRICS = ["min", "max", "mean", "std", "count"]


def array_stats(values: np.ndarray, *, quantiles: bool = True) -> dict[str, list]:
    """min / max / mean / std / count (and, with `quantiles`, the QUANTILES) over the first axis of (N, D)
    values; each a list of D numbers, count [N]."""
    values = np.asarray(values, dtype=np.float64)
    stats = {
        "min": values.min(0).tolist(),
        "max": values.max(0).tolist(),
        "mean": values.mean(0).tolist(),
        "std": values.std(0).tolist(),
        "count": [int(values.shape[0])],
    }
    if quantiles:
        levels = np.quantile(values, list(QUANTILES.values()), axis=0, method="inverted_cdf")
        stats.update({key: level.tolist() for key, level in zip(QUANTILES, levels)})
    return stats


def image_stats(frames: np.ndarray, *, frame_stride: int = 5, pixel_stride: int = 4,
                quantiles: bool = True) -> dict[str, list]:
    """Per-channel statistics of uint8 (T, H, W, 3) frames scaled to [0, 1], each shaped (3, 1, 1) as lerobot
    stores them (count: [frames sampled]); computed on every `frame_stride`-th frame and pixel grid point."""
    sample = np.asarray(frames)[::frame_stride, ::pixel_stride, ::pixel_stride].reshape(-1, 3) / 255.0
    stats = array_stats(sample, quantiles=quantiles)
    shaped = {k: [[[v]] for v in values] for k, values in stats.items() if k != "count"}
    shaped["count"] = [int(len(frames[::frame_stride]))]
    return shaped


def has_quantiles(stats: dict) -> bool:
    """Whether one feature's statistics ({metric: value}) carry every one of the QUANTILES."""
    return all(key in stats for key in QUANTILES)


def without_quantiles(stats: dict) -> dict:
    """One feature's statistics without the QUANTILES (what a dataset written before they were records)."""
    return {k: v for k, v in stats.items() if k not in QUANTILES}


def aggregate_stats(per_episode: list[dict[str, dict]]) -> dict[str, dict]:
    """Combine per-episode statistics into dataset statistics: extremes of the extremes, the count-weighted mean,
    the pooled standard deviation, the summed count, and each quantile as the count-weighted mean of the parts'
    (only where every part has it)."""
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
        for q in QUANTILES:
            if all(q in p for p in parts):
                levels = np.stack([np.asarray(p[q], dtype=np.float64) for p in parts])
                out[key][q] = (weights * levels).sum(0).tolist()
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
