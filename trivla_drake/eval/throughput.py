"""`bench --throughput`: how fast the data pipeline runs at 1 and 2 workers: collect (demonstrations per minute, plain
and with chain preludes), the feature cache (episodes per minute), policy-stage training (steps per second at batch 32)
and evaluation (episodes per minute).

Each figure runs the product's own job on a fresh temporary folder, on a local Ray started before the clock starts
(its start-up, a few seconds once per command, is reported on its own): the rates are what a long run reaches.
"""

from __future__ import annotations

import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

from trivla_drake.eval.throughput_config import ThroughputConfig


@contextmanager
def _workers(count: int):
    """A local Ray with `count` worker CPUs for the jobs inside (none for 1); yields its start-up time [s]."""
    if count == 1:
        yield 0.0
        return
    import ray

    from trivla_drake.eval.rollout_runner import start_local_ray

    start = time.perf_counter()
    start_local_ray(count)
    try:
        yield time.perf_counter() - start
    finally:
        ray.shutdown()


def measure_collect(config: ThroughputConfig, workers: int, *, prelude: bool, out: Path) -> dict:
    """`collect` of `config.collect_episodes_per_task` oracle demonstrations of every task into `out` (plain, or each
    after a chain prelude of 1 to 4 tasks): demonstrations per minute."""
    from trivla_drake.eval.collect import collect
    from trivla_drake.eval.collect_config import CollectConfig

    collect_config = CollectConfig(out=str(out), episodes_per_task=config.collect_episodes_per_task, workers=workers,
                                   tasks=list(config.tasks), prelude_tasks=4 if prelude else 0,
                                   seed=config.seed)
    with _workers(workers) as ray_start:
        start = time.perf_counter()
        summary = collect(collect_config, progress=False)
        seconds = time.perf_counter() - start
    return {"demonstrations": summary["episodes"], "seconds": seconds, "ray_start_seconds": ray_start,
            "per_minute": 60.0 * summary["episodes"] / seconds}


def measure_evaluate(config: ThroughputConfig, workers: int) -> dict:
    """`evaluate` of the shipped model (or `config.policy`), `config.evaluate_episodes` episodes of every task:
    episodes per minute."""
    from trivla_drake.eval.evaluate import EvalConfig, evaluate

    eval_config = EvalConfig(policy=config.policy, tasks=list(config.tasks), episodes=config.evaluate_episodes,
                             workers=workers)
    with _workers(workers) as ray_start:
        start = time.perf_counter()
        report = evaluate(eval_config, progress=False)
        seconds = time.perf_counter() - start
    episodes = sum(row["episodes"] for row in report["tasks"].values())
    return {"episodes": episodes, "seconds": seconds, "ray_start_seconds": ray_start,
            "per_minute": 60.0 * episodes / seconds, "average_success": report["average_success"]}


def run_throughput(config: ThroughputConfig, *, progress: bool = True) -> dict:
    """Every figure of `config` at each of `config.workers`: {"collect": {W: ...}, "collect_prelude": ...,
    "feature_cache": ..., "training": ..., "evaluate": ...}."""
    config.validate()
    from tqdm import tqdm

    from trivla_drake.train.throughput import measure_feature_cache, measure_training_steps

    stages = [name for name in ("collect", "collect_prelude", "feature_cache", "training", "evaluate")
              if name in config.measure]
    result: dict = {"workers": list(config.workers), "config": _config_dict(config)}
    bar = tqdm(total=len(stages) * len(config.workers), desc="throughput", disable=not progress)
    with tempfile.TemporaryDirectory(prefix="trivla-throughput-") as folder:
        root = Path(folder)
        for workers in config.workers:
            dataset = root / f"plain-{workers}"
            for stage in stages:
                bar.set_postfix_str(f"{stage}, {workers} worker{'s' * (workers > 1)}")
                if stage == "collect":
                    figure = measure_collect(config, workers, prelude=False, out=dataset)
                elif stage == "collect_prelude":
                    figure = measure_collect(config, workers, prelude=True, out=root / f"prelude-{workers}")
                elif stage == "feature_cache":
                    figure = measure_feature_cache(_dataset(config, dataset), episodes=config.cache_episodes,
                                                   workers=workers)
                elif stage == "training":
                    figure = measure_training_steps(_dataset(config, dataset), steps=config.training_steps,
                                                    batch_size=config.batch_size, workers=workers)
                else:
                    figure = measure_evaluate(config, workers)
                result.setdefault(stage, {})[str(workers)] = figure
                bar.update(1)
    bar.close()
    return result


def _dataset(config: ThroughputConfig, path: Path) -> Path:
    """`path`, collected (serially) if the collect figure did not run first."""
    if not (path / "meta" / "info.json").is_file():
        measure_collect(config, 1, prelude=False, out=path)
    return path


def _config_dict(config: ThroughputConfig) -> dict:
    from dataclasses import asdict

    return asdict(config)


# What each figure is, for the table: (stage, its rate's key, unit).
ROWS = [
    ("collect", "per_minute", "collect: demonstrations / min"),
    ("collect_prelude", "per_minute", "collect with chain preludes: demonstrations / min"),
    ("feature_cache", "per_minute", "feature cache: episodes / min"),
    ("training", "steps_per_second", "policy training: steps / s (batch {batch})"),
    ("evaluate", "per_minute", "evaluate ({policy}): episodes / min"),
]


def format_throughput(result: dict) -> str:
    """The figures as a Markdown table: one row per figure, one column per worker count, and the speed-up."""
    workers = [str(w) for w in result["workers"]]
    config = result["config"]
    header = "| figure | " + " | ".join(f"{w} worker{'s' * (w != '1')}" for w in workers) + \
        (f" | {workers[-1]} / {workers[0]} |" if len(workers) > 1 else " |")
    lines = [header, "| --- |" + " --- |" * (len(workers) + (len(workers) > 1))]
    for stage, key, label in ROWS:
        if stage not in result:
            continue
        values = [result[stage][w][key] for w in workers]
        cells = " | ".join(f"{v:.2f}" for v in values)
        ratio = f" | {values[-1] / values[0]:.2f}x" if len(values) > 1 and values[0] else ""
        lines.append(f"| {label.format(batch=config['batch_size'], policy=config['policy'])} | {cells}{ratio} |")
    return "\n".join(lines)
