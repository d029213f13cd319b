"""`BenchConfig`, what `bench` times: diff-IK, the station and the closed loop, or with `model` the TriVLA model's
per-system latency (loadable from YAML: `trivla-drake bench --config FILE --set k=v`)."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc
from typing import Optional

from trivla_drake.eval.setting_checks import check_seconds
from trivla_drake.eval.throughput_config import ThroughputConfig

# Autocast dtypes `bench --model` times (nn/benchmark.py's PRECISIONS; named here so that the config needs no torch).
PRECISIONS = ("float32", "bfloat16", "float16")


@dc.dataclass
class BenchConfig:
    """What `bench` times."""

    # Benchmark the TriVLA model (per-system latency, Table 4's shape) instead of the station.
    model: bool = False
    # Measure the data pipeline's throughput instead (collect, feature cache, training, evaluate at 1 and 2 workers).
    throughput: bool = False
    # What the throughput figures run (with `throughput`).
    pipeline: ThroughputConfig = dc.field(default_factory=ThroughputConfig)
    # Model preset (tiny, cpu, paper): with `model`, the preset timed (None: cpu); without, an UNTRAINED model of it
    # for the closed-loop figure instead of the shipped checkpoint.
    preset: Optional[str] = None
    # TriVLA checkpoint for the closed-loop figure (None: models/trivla_cpu, else an untrained cpu model).
    checkpoint: Optional[str] = None
    # With `model`: autocast dtype of the timed calls (weights stay float32): float32, bfloat16 or float16.
    precision: str = "float32"
    # Simulated time per station run [s].
    seconds: float = 4.0
    # Diff-IK problems to time.
    diffik_problems: int = 2000
    # Scenarios YAML file (None: models/default.scenarios.yaml).
    scenario: Optional[str] = None
    # Torch threads in the closed loop (1: physics and rendering share the cores).
    threads: int = 1

    def validate(self) -> None:
        """ValueError naming the flag or field of a setting that cannot run."""
        if self.model and self.throughput:
            raise ValueError("--model and --throughput are two different benchmarks: give one")
        if self.throughput:
            self.pipeline.validate()
        check_seconds(self.seconds, "seconds")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        if self.precision != "float32" and not self.model:
            raise ValueError("precision goes with --model (the station benchmarks run the model in float32)")
        if self.diffik_problems < 1:
            raise ValueError(f"diffik_problems must be at least 1, got {self.diffik_problems}")
        if self.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.threads}")
