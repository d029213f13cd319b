"""One timed feature-cache run for compare.py, with whichever trivla_drake is first on the path (the old tree's or
this one's): the shipped model's System 2/3 features of the first N episodes of DATASET at the recipe's stride (3),
into a fresh folder, with W workers (old code: W torch threads; new code: W worker threads of one torch thread each).

    python research/throughput/cache_run.py DATASET W N      # prints one JSON line
"""

import inspect
import json
import sys
import tempfile
import time

import torch

from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.nn import load_checkpoint
from trivla_drake.train import features
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.distributed import DistEnv


def main() -> int:
    dataset, workers, episodes = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    model = load_checkpoint("models/trivla_cpu").eval()
    reader = LeRobotReader(dataset)
    with tempfile.TemporaryDirectory() as cache:
        config = TrainConfig(stage="policy", data=dataset, out=cache + "/unused", cache_dir=cache)
        config.features.stride = 3
        has_workers = "workers" in inspect.signature(features.ensure_feature_cache).parameters
        torch.set_num_threads(workers)
        kwargs = {"workers": workers} if has_workers else {}
        start = time.perf_counter()
        features.ensure_feature_cache(model, reader, list(range(episodes)), config, DistEnv(), progress=False, **kwargs)
        seconds = time.perf_counter() - start
    print(json.dumps({"episodes": episodes, "seconds": seconds, "per_minute": 60 * episodes / seconds}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
