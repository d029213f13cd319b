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

`YawTwists` is a second, targeted disturbance: once per episode, while the open hand comes down to
its first grasp, its yaw is turned 17-43 degrees away from the expert's (the rotation the expert
commands is replaced for those steps). The expert (with `OraclePolicy(turn_first=True)`) then
holds its position until it has turned back, and only then goes down. A learned policy that comes
near a block turned off its faces finds such states in the data, with the turn that recovers; in
clean demonstrations the hand is always turned right before it is near (results/grasp_yaw).

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
    """Settings of a disturbance of the applied actions (bursts, yaw twists, missed grasps, approach
    drifts); `start(rng)` begins one episode's."""

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
            raise ValueError(f"--action-noise must be in [0, {1.0 / cls.rate:.1f}], got {scale}")
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
        """`observation` is not used (the interface of `YawTwistState.apply`)."""
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


# What `descent_below` tells a once-per-episode disturbance.
WAITING, STARTED, PAST = "waiting", "started", "past"


def descent_below(action: np.ndarray, observation: dict | None, start_z: float, who: str) -> str:
    """Whether the expert's `action` (7,) starts the one disturbance of an episode that waits for the open
    hand to come down to its first grasp: PAST once the gripper is commanded closed (the first grasp
    began), STARTED when the action goes down while observation['ee_target'] (4x4, the commanded tcp
    pose) is below `start_z` [m], else WAITING. ValueError naming `who` without the commanded pose."""
    if action[6] <= 0.0:
        return PAST
    if observation is None or "ee_target" not in observation:
        raise ValueError(f"{who} needs observation['ee_target'] (the commanded tcp pose)")
    if action[2] < 0.0 and float(np.asarray(observation["ee_target"])[2, 3]) < start_z:
        return STARTED
    return WAITING


@dataclass(frozen=True)
class YawTwists:
    """Settings of the yaw twist (see the module docstring)."""

    # The twist starts the first time the commanded tcp, descending with the gripper open and before
    # the gripper first closes, is below a height drawn uniformly from this range [m].
    start_z: tuple[float, float] = (0.06, 0.14)
    # Total twist [rad], drawn uniformly; the sign is drawn too.
    angle: tuple[float, float] = (0.3, 0.75)
    # Rotation about the world's vertical per step while twisting [rad]; the step's translation stays the expert's.
    rate: float = 0.04

    def __post_init__(self) -> None:
        if not 0.0 < self.start_z[0] <= self.start_z[1]:
            raise ValueError(f"yaw twist start_z range must be 0 < low <= high, got {self.start_z}")
        if not 0.0 < self.angle[0] <= self.angle[1] < np.pi / 4:
            raise ValueError(f"yaw twist angle range must be 0 < low <= high < pi/4, got {self.angle}")
        if not 0.0 < self.rate <= 0.05:
            raise ValueError(f"yaw twist rate must be in (0, 0.05] rad per step, got {self.rate}")

    def start(self, rng: np.random.Generator) -> "YawTwistState":
        """A fresh twist for one episode, drawing from `rng`."""
        return YawTwistState(self, rng)


class YawTwistState:
    """The twist of one episode: `apply(action, observation)` -> (applied action, disturbed?).

    `observation['ee_target']` (4x4, the executor's commanded tcp pose) tells the height."""

    def __init__(self, settings: YawTwists, rng: np.random.Generator) -> None:
        self.settings = settings
        self.start_z = float(rng.uniform(*settings.start_z))
        angle = float(rng.uniform(*settings.angle))
        self.steps = int(np.ceil(angle / settings.rate))
        self.step_rate = float(rng.choice([-1.0, 1.0])) * angle / self.steps
        self.remaining = -1  # -1: not started; then the steps left; 0: done (or never, past the first close)

    def apply(self, action: np.ndarray, observation: dict | None = None) -> tuple[np.ndarray, bool]:
        if self.remaining == -1:
            when = descent_below(action, observation, self.start_z, "YawTwists")
            if when != WAITING:
                self.remaining = self.steps if when == STARTED else 0  # PAST: this episode is not twisted
        if self.remaining <= 0:
            return action, False
        self.remaining -= 1
        applied = np.array(action, dtype=float)
        applied[3:6] = (0.0, 0.0, self.step_rate)
        return applied, True
