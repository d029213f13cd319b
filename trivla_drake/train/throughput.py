"""How fast the policy stage's data path runs, for `bench --throughput` (eval/throughput.py): the feature cache in
episodes per minute and policy-stage training in steps per second, each at a given number of workers, on a fresh
temporary folder (nothing of the caller's cache is read or written).

- `measure_feature_cache`: `ensure_feature_cache` of the first `episodes` episodes of a dataset with the shipped
  model (or another checkpoint / model), `workers` episodes at a time (train/features.py: each worker a thread with
  one torch thread), at the shipped recipe's feature stride (3). The clock covers the caching alone (keys, video
  decoding, System 2 and 3, the shards written), not loading the model.
- `measure_training_steps`: `train` (the product's own loop) of the policy stage from the shipped checkpoint, as the
  recipe's "follow" stages run it (grounding weight 1, phase follow), with `workers` torch threads. The clock covers
  `steps` steps after `warmup_steps`, not preparing the data (caching its features, which a coarse
  `feature_stride` keeps short: a step's cost does not depend on it) nor the final checkpoint.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

RECIPE_FEATURE_STRIDE = 3  # the shipped recipe's features.stride (recipes/trivla_cpu.yaml)


def _positive(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1; got {value!r}")
    return value


def _checkpoint_dir(checkpoint: str | os.PathLike | None) -> Path:
    if checkpoint is not None:
        return Path(checkpoint)
    from trivla_drake.eval.model_loading import default_checkpoint_dir

    return default_checkpoint_dir()


class _TorchThreads:
    """torch's intra-op thread count set for a block, then restored."""

    def __init__(self, count: int) -> None:
        self.count = count

    def __enter__(self) -> None:
        self.before = torch.get_num_threads()
        torch.set_num_threads(self.count)

    def __exit__(self, *exc: object) -> None:
        torch.set_num_threads(self.before)


def measure_feature_cache(dataset_dir: str | os.PathLike, *, episodes: int = 12, workers: int = 1,
                          model: Any = None, feature_stride: int = RECIPE_FEATURE_STRIDE) -> dict[str, Any]:
    """Caches the System 2/3 features of the first `episodes` episodes of `dataset_dir` into a temporary folder
    with `workers` workers (module doc). `model`: a TriVLA, a checkpoint folder, or None for the shipped one.
    Returns {"episodes", "frames", "seconds", "per_minute" (episodes), "frames_per_second", "cpu_seconds" (of this
    process, all threads), "workers", "feature_stride"}."""
    from trivla_drake.data.lerobot_reader import LeRobotReader
    from trivla_drake.nn.trivla import TriVLA
    from trivla_drake.train.config import TrainConfig
    from trivla_drake.train.distributed import DistEnv
    from trivla_drake.train.features import ensure_feature_cache

    _positive(episodes, "episodes")
    _positive(workers, "workers")
    _positive(feature_stride, "feature_stride")
    reader = LeRobotReader(dataset_dir)
    chosen = list(range(min(episodes, reader.num_episodes)))
    if not chosen:
        raise ValueError(f"dataset {dataset_dir} has no episodes to cache")
    if not isinstance(model, TriVLA):
        from trivla_drake.nn import load_checkpoint

        model = load_checkpoint(str(_checkpoint_dir(model)))
    if model.vision_language is None and model.dynamics is None:
        raise ValueError("the model has neither System 2 nor System 3: it caches no features")
    frames = sum(-(-int(reader.episodes[e]["length"]) // feature_stride) for e in chosen)
    with tempfile.TemporaryDirectory(prefix="trivla-cache-throughput-") as folder, _TorchThreads(workers):
        config = TrainConfig(stage="policy", data=str(dataset_dir), out=str(Path(folder) / "run"),
                             cache_dir=str(Path(folder) / "cache"), progress=False)
        config.features.stride = feature_stride
        start, cpu_start = time.perf_counter(), time.process_time()
        _, summary = ensure_feature_cache(model, reader, chosen, config, DistEnv(), progress=False, workers=workers)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    return {"episodes": len(chosen), "frames": frames, "seconds": seconds, "per_minute": 60.0 * len(chosen) / seconds,
            "frames_per_second": frames / seconds, "cpu_seconds": cpu, "workers": summary["feature_cache_workers"],
            "feature_stride": feature_stride}


def measure_training_steps(dataset_dir: str | os.PathLike, *, steps: int = 20, batch_size: int = 32, workers: int = 1,
                           warmup_steps: int = 2, checkpoint: str | os.PathLike | None = None,
                           feature_stride: int = 12) -> dict[str, Any]:
    """Policy-stage training on `dataset_dir` from `checkpoint` (None: the shipped one) with `workers` torch threads
    and batches of `batch_size`, in a temporary folder (module doc): `steps` steps timed after `warmup_steps`.
    Returns {"steps", "batch_size", "seconds", "steps_per_second", "samples_per_second", "median_step_seconds",
    "workers", "prepare_seconds" (caching the features and the rest before the first step)}."""
    import numpy as np

    from trivla_drake.nn.checkpoint import read_checkpoint_config
    from trivla_drake.train.config import TrainConfig
    from trivla_drake.train.trainer import train

    _positive(steps, "steps")
    _positive(batch_size, "batch_size")
    _positive(workers, "workers")
    _positive(feature_stride, "feature_stride")
    _positive(warmup_steps, "warmup_steps")  # the first step also sets up lazily made kernels
    source = _checkpoint_dir(checkpoint)
    grounding = bool(read_checkpoint_config(str(source))["config"].get("policy", {}).get("instruction_grounding"))
    ticks: list[float] = []
    with tempfile.TemporaryDirectory(prefix="trivla-train-throughput-") as folder:
        # One step past the timed ones: the last step's time includes writing the final checkpoint.
        config = TrainConfig(stage="policy", data=str(dataset_dir), out=str(Path(folder) / "run"), init=str(source),
                             steps=warmup_steps + steps + 1, batch_size=batch_size, threads=workers,
                             cache_dir=str(Path(folder) / "cache"), progress=False, checkpoint_every=10**9,
                             keep_checkpoints=1)
        config.features.stride = feature_stride
        if grounding:  # as the recipe's follow stages train the shipped model
            config.policy.grounding.weight, config.policy.grounding.phase = 1.0, "follow"
        with _TorchThreads(torch.get_num_threads()):  # train() sets threads=workers; restored after
            summary = train(config, step_callback=lambda step: ticks.append(time.perf_counter()))
    timed = ticks[warmup_steps - 1 : warmup_steps + steps]  # ticks[k]: when step k + 1 ended
    seconds = timed[-1] - timed[0]
    return {"steps": steps, "batch_size": batch_size, "seconds": seconds, "steps_per_second": steps / seconds,
            "samples_per_second": steps * batch_size / seconds,
            "median_step_seconds": float(np.median(np.diff(timed))), "workers": workers,
            "prepare_seconds": summary["data_prepare_s"]}
