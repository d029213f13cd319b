"""Latency-aware inference timing: when a periodic inference's result becomes visible in sim time.

A real robot sees a network's answer only after the network has run. Here an inference started at
simulated time t publishes its result at t + latency, where latency is zero, a fixed number of
seconds, or the wall time the inference really took. While an inference is "running" (its result
not yet visible), the next periodic tick does not start another one, as on a real machine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

# Sim times within this of each other [s] are one instant: an inference started at tick t_n with a
# delay of one period is ready at the next tick, though t_n + period may round a float step above
# Drake's t_(n+1) (about 5% of the ticks of a 10/36 s period would otherwise skip an inference).
TIME_TOLERANCE_S = 1e-9


@dataclass(frozen=True)
class LatencyModel:
    """`mode` is "zero", "fixed" (`seconds` of delay) or "measured" (the inference's wall time)."""

    mode: str = "zero"
    seconds: float = 0.0

    def __post_init__(self):
        if self.mode not in ("zero", "fixed", "measured"):
            raise ValueError(f"latency mode must be 'zero', 'fixed' or 'measured', got {self.mode!r}")
        if not self.seconds >= 0.0:
            raise ValueError(f"latency seconds must be >= 0, got {self.seconds}")

    @staticmethod
    def parse(text: str) -> "LatencyModel":
        """From a command-line word: `zero`, `measured` or a number of seconds."""
        if text in ("zero", "measured"):
            return LatencyModel(text)
        try:
            seconds = float(text)
        except ValueError:
            seconds = float("nan")
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"--latency must be 'zero', 'measured' or a finite number of seconds >= 0, got {text!r}")
        return LatencyModel("fixed", seconds)

    def delay(self, wall_seconds: float) -> float:
        """Simulated delay [s] for an inference that took `wall_seconds` of wall time."""
        if self.mode == "zero":
            return 0.0
        return self.seconds if self.mode == "fixed" else wall_seconds


@dataclass(frozen=True)
class InferenceSlots:
    """What a system has published (`current`, stamped with its observation time) and what is still
    in flight (`pending`, visible from `ready_time`). Lives in the Context's abstract state."""

    current: Any = None
    current_stamp: float = float("nan")  # sim time of the observation `current` was computed from
    pending: Any = None
    pending_stamp: float = float("nan")
    ready_time: float = float("inf")  # when `pending` becomes visible; inf: nothing in flight
    count: int = 0  # inferences started so far (seeds each one)

    def visible(self, t: float) -> tuple[Any, float]:
        """(value, observation time) visible at sim time t."""
        if self.pending is not None and self.ready(t):
            return self.pending, self.pending_stamp
        return self.current, self.current_stamp

    def ready(self, t: float) -> bool:
        """True when `pending`'s ready time has come at sim time t (to within TIME_TOLERANCE_S)."""
        return t >= self.ready_time - TIME_TOLERANCE_S

    def busy(self, t: float) -> bool:
        """True while an inference started earlier has not yet published."""
        return self.pending is not None and not self.ready(t)

    def settle(self, t: float) -> "InferenceSlots":
        """Move a pending result that is visible at t into `current`."""
        if self.pending is None or not self.ready(t):
            return self
        return replace(self, current=self.pending, current_stamp=self.pending_stamp,
                       pending=None, pending_stamp=float("nan"), ready_time=float("inf"))

    def start(self, t: float, value: Any, delay: float) -> "InferenceSlots":
        """Record an inference on the observation at t whose result shows from t + delay."""
        return replace(self, pending=value, pending_stamp=t, ready_time=t + delay, count=self.count + 1)
