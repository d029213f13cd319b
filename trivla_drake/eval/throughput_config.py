"""`ThroughputConfig`, what `bench --throughput` measures (loadable from YAML as `bench`'s `pipeline` block:
`trivla-drake bench --throughput --set pipeline.workers=[1,2]`)."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc

from trivla_drake.tasks.suite import TASK_NAMES

# The figures `bench --throughput` can measure.
MEASURES = ["collect", "collect_prelude", "feature_cache", "training", "evaluate"]


@dc.dataclass
class ThroughputConfig:
    """What `bench --throughput` measures."""

    # Worker counts to measure each figure at (processes: a local Ray for collect and evaluate).
    workers: list[int] = dc.field(default_factory=lambda: [1, 2])
    # The figures to measure (all by default): collect, collect_prelude, feature_cache, training, evaluate.
    measure: list[str] = dc.field(default_factory=lambda: list(MEASURES))
    # Tasks of the collect and evaluate figures (all by default).
    tasks: list[str] = dc.field(default_factory=lambda: list(TASK_NAMES))
    # Demonstrations per task collected per worker count (a larger count amortises the last, slowest attempts).
    collect_episodes_per_task: int = 2
    # Base seed of the demonstrations.
    seed: int = 0
    # Episodes of the collected dataset cached for the feature-cache figure.
    cache_episodes: int = 12
    # Policy-stage training steps timed (after warm-up steps).
    training_steps: int = 20
    # Training batch size.
    batch_size: int = 32
    # The policy evaluated: 'trivla' (the shipped checkpoint), a checkpoint folder, or 'oracle'.
    policy: str = "trivla"
    # Episodes per task evaluated per worker count.
    evaluate_episodes: int = 1

    def validate(self) -> None:
        """ValueError naming the field of a setting that cannot run."""
        if not self.workers or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in self.workers):
            raise ValueError(f"pipeline.workers must be a non-empty list of integers >= 1, got {self.workers}")
        unknown = [m for m in self.measure if m not in MEASURES]
        if unknown or not self.measure:
            raise ValueError(f"pipeline.measure: {unknown or 'empty'}; choose from {', '.join(MEASURES)}")
        for name in ("collect_episodes_per_task", "cache_episodes", "training_steps", "batch_size",
                     "evaluate_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"pipeline.{name} must be an integer >= 1, got {value!r}")
        from trivla_drake.tasks.run_settings import check_run_settings

        check_run_settings(self.tasks, self.seed)
