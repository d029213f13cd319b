"""The policy-facing action space.

This module is the one place the action is defined; the dataset, the oracle, the random policy,
learned policies and `trivla_drake.systems.action_executor` (its adapter onto the station's ports)
all use it. It imports no Drake, so the task suite and the CLI's parser load without it.

Action (7 floats, one per control step, applied at `control_rate_hz`, default 36 Hz, the paper's
control frequency):

    [dx, dy, dz, drx, dry, drz, gripper]

- dx, dy, dz [m]: translation of the commanded tool-centre point (`panda_hand_tcp`) in the
  robot's base frame B, `panda_link0` (x away from the robot, y to its left, z up; the station welds
  the base at the world origin, so there B is the world; elsewhere `ee_target` = X_WB times the pose in B).
- drx, dry, drz [rad]: rotation increment as an axis-angle vector in base-frame axes, applied to the
  commanded tcp orientation by left multiplication: R_next = Exp([drx, dry, drz]) R.
- gripper: > 0 opens the hand (fingers 0.08 m apart), <= 0 closes it (commanded width 0; the
  fingers squeeze whatever is between them). Demonstrations only contain +1 and -1.

The deltas are relative to the *commanded* pose (the executor's state), not the measured one:
target_{k+1} = target_k (+) action_k, with target_0 the measured tcp pose when the episode starts.
So the commanded path is exactly the integral of the actions (a replay reproduces it), and a
policy that outputs zeros holds its pose. Each component is clipped to +/- `max_translation`
(0.01 m per step, 0.36 m/s) and +/- `max_rotation` (0.05 rad per step, 1.8 rad/s), and the
commanded position is clamped into `workspace_low/high`, so no action can wind the target up far
from where the arm can go.

Normalisation: `ACTION_LOW` / `ACTION_HIGH` are the fixed bounds above (a policy may map [-1, 1]
onto them); the dataset additionally records measured per-dimension min/max/mean/std in
`meta/stats.json` (lerobot's MIN_MAX and MEAN_STD modes), which a learned policy should use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACTION_NAMES = ("dx", "dy", "dz", "drx", "dry", "drz", "gripper")
ACTION_DIM = 7
GRIPPER_OPEN, GRIPPER_CLOSE = 1.0, -1.0


@dataclass(frozen=True)
class ActionSpace:
    """Settings of the relative end-effector action; every default is what the datasets use."""

    # Control rate: one action per 1/control_rate_hz seconds [Hz] (the paper's 36 Hz).
    control_rate_hz: float = 36.0
    # Largest translation per step and component [m].
    max_translation: float = 0.01
    # Largest rotation increment per step and component [rad].
    max_rotation: float = 0.05
    # Box the commanded tcp position is kept in [m] (robot base frame).
    workspace_low: tuple[float, float, float] = (0.1, -0.6, 0.005)
    workspace_high: tuple[float, float, float] = (0.9, 0.6, 0.7)

    @property
    def dt(self) -> float:
        """Control period [s]."""
        return 1.0 / self.control_rate_hz

    @property
    def low(self) -> np.ndarray:
        """Lower bound of each action component."""
        t, r = self.max_translation, self.max_rotation
        return np.array([-t, -t, -t, -r, -r, -r, -1.0])

    @property
    def high(self) -> np.ndarray:
        """Upper bound of each action component."""
        return -self.low


DEFAULT_ACTION_SPACE = ActionSpace()
ACTION_LOW = DEFAULT_ACTION_SPACE.low
ACTION_HIGH = DEFAULT_ACTION_SPACE.high


def check_action(action, name: str = "action") -> np.ndarray:
    """`action` as a float (7,) array; ValueError naming it if it has another shape or NaN/inf."""
    array = np.asarray(action, dtype=float)
    if array.shape != (ACTION_DIM,):
        raise ValueError(f"{name} must have shape ({ACTION_DIM},) {ACTION_NAMES}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} has NaN or infinite entries: {array}")
    return array
