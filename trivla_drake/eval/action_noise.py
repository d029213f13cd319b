"""Perturbation bursts for demonstration collection (DART, Laskey et al. 2017).

A behaviour-cloned policy drifts off the demonstrated paths, into states no demonstration shows,
and does not know how to come back. DART collects demonstrations in which the *applied* action is
disturbed now and then while the *recorded* action stays the expert's, so the data set shows the
expert correcting from off-path states.

`PerturbationBursts` disturbs the arm in short bursts: at each control step outside a burst, one
starts with probability `rate`; it lasts `min_steps`..`max_steps` steps, during which a constant
end-effector velocity (random direction, `speed` m per step; rotation with `turn` rad per step
standard deviation per axis) is added to the expert's action. The gripper is never disturbed.
Between bursts the expert's actions are applied unchanged, so it reaches its waypoints exactly.

Which steps were disturbed is recorded (`Trajectory.perturbed`): a recorded action that comes after
a disturbed step answers a state the earlier frame does not show, so training masks it out of that
frame's action chunk (see `trivla_drake.data.samples`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


class DisturbanceState(Protocol):
    """One episode's running disturbance: `apply(action, observation)` -> (applied action, disturbed?)."""

    def apply(self, action: np.ndarray, observation: dict | None = None) -> tuple[np.ndarray, bool]: ...


class Disturbance(Protocol):
    """Settings of a disturbance of the applied actions (a registered perturbation, eval/perturbations.py);
    `start(rng)` begins one episode's."""

    def start(self, rng: np.random.Generator) -> DisturbanceState: ...


@dataclass(frozen=True)
class PerturbationBursts:
    """Settings of the bursts (see the module docstring); `scaled(x)` gives the defaults x times as often."""

    # Probability per control step that a burst starts (outside a burst).
    rate: float = 0.06
    min_steps: int = 4
    max_steps: int = 10
    # Translation added per step during a burst [m], drawn uniformly in this range.
    speed: tuple[float, float] = (0.002, 0.005)
    # Standard deviation of the rotation added per step about x, y, z [rad].
    turn: tuple[float, float, float] = (0.004, 0.004, 0.015)

    def __post_init__(self) -> None:
        if not 0.0 <= self.rate <= 1.0:
            raise ValueError(f"action noise rate must be in [0, 1], got {self.rate}")
        if not 1 <= self.min_steps <= self.max_steps:
            raise ValueError(f"burst length needs 1 <= min_steps <= max_steps, got {self.min_steps}, {self.max_steps}")
        if not 0.0 <= self.speed[0] <= self.speed[1]:
            raise ValueError(f"burst speed range must be 0 <= low <= high, got {self.speed}")

    @classmethod
    def scaled(cls, scale: float) -> "PerturbationBursts":
        """The default bursts, `scale` times as often (0 never disturbs)."""
        if not 0.0 <= scale <= 1.0 / cls.rate:
            raise ValueError(f"scale must be in [0, {1.0 / cls.rate:.1f}], got {scale}")
        return cls(rate=cls.rate * scale)

    def start(self, rng: np.random.Generator) -> "BurstState":
        """A fresh disturbance process for one episode, drawing from `rng`."""
        return BurstState(self, rng)


class BurstState:
    """The running disturbance of one episode: `apply(action)` -> (applied action, disturbed?)."""

    def __init__(self, settings: PerturbationBursts, rng: np.random.Generator) -> None:
        self.settings, self.rng = settings, rng
        self.remaining = 0
        self.velocity = np.zeros(6)

    def apply(self, action: np.ndarray, observation: dict | None = None) -> tuple[np.ndarray, bool]:
        """`observation` is not used (the interface of `DisturbanceState.apply`)."""
        s, rng = self.settings, self.rng
        if self.remaining == 0 and rng.random() < s.rate:
            self.remaining = int(rng.integers(s.min_steps, s.max_steps + 1))
            direction = rng.normal(size=3)
            direction /= max(float(np.linalg.norm(direction)), 1e-12)
            self.velocity = np.concatenate([direction * rng.uniform(*s.speed), rng.normal(size=3) * np.asarray(s.turn)])
        if self.remaining == 0:
            return action, False
        self.remaining -= 1
        applied = np.array(action, dtype=float)
        applied[:6] += self.velocity
        return applied, True
