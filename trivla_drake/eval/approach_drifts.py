"""Approach drifts for demonstration collection: the hand is pushed off the block on its way down, and
the expert centres it again from the wrist view's offset before it goes on down.

The shipped policy's grasps fail because its hand arrives 1-3 cm off the named block and turned off
its faces (results/grasp_yaw, results/missed_grasps), and then goes on down. In clean
demonstrations the expert always comes down straight above the block, so near it the block sits in
the middle of the wrist view in every frame: a linear probe of System 2's wrist tokens finds the
block's offset from the hand there to 0.4 cm only because it is always about zero (its spread is
0.8-1 cm), and nothing shows what to do when it is not. `ApproachDrifts` makes such frames, with
the answer.

Once per episode, the first time the commanded tool-centre point comes down with the gripper open
below a height drawn from `start_z` (before the gripper first closes), the applied actions are
replaced for a few steps: the commanded tcp moves sideways by `offset` metres (drawn) in a drawn
direction, holding its height, while it turns `turn` radians about the vertical (drawn, either
sign). The expert (with `OraclePolicy(align_first=True)`) then stops going down while its hand is
more than `oracle.ALIGN_FIRST_M` sideways or `oracle.TURN_FIRST_RAD` turned off its grasp, moves
back above the block and turns back, and only then goes on down. The recorded actions stay the
expert's and the replaced steps are marked disturbed (`Trajectory.perturbed`), so training uses the
expert's answer to those frames and masks the rest of their chunks (`trivla_drake.data.samples`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trivla_drake.eval.action_noise import STARTED, WAITING, descent_below
from trivla_drake.systems.action_executor import ACTION_DIM, DEFAULT_ACTION_SPACE, GRIPPER_OPEN


@dataclass(frozen=True)
class ApproachDrifts:
    """Settings of the drift (see the module docstring)."""

    # The drift starts the first time the commanded tcp, descending with the gripper open and before the
    # gripper first closes, is below a height drawn uniformly from this range [m].
    start_z: tuple[float, float] = (0.06, 0.13)
    # Sideways distance of the drift [m], drawn uniformly; its direction is drawn uniformly too.
    offset: tuple[float, float] = (0.012, 0.035)
    # Turn of the hand about the vertical during the drift [rad], drawn uniformly; the sign is drawn too.
    turn: tuple[float, float] = (0.0, 0.6)
    # Sideways speed of the commanded tcp while drifting [m per step].
    speed: float = 0.003

    def __post_init__(self) -> None:
        if not 0.0 < self.start_z[0] <= self.start_z[1]:
            raise ValueError(f"approach drift start_z range must be 0 < low <= high, got {self.start_z}")
        if not 0.0 < self.offset[0] <= self.offset[1]:
            raise ValueError(f"approach drift offset range must be 0 < low <= high, got {self.offset}")
        if not 0.0 <= self.turn[0] <= self.turn[1] < np.pi / 4:
            raise ValueError(f"approach drift turn range must be 0 <= low <= high < pi/4, got {self.turn}")
        if not 0.0 < self.speed <= DEFAULT_ACTION_SPACE.max_translation:
            raise ValueError(f"approach drift speed must be in (0, {DEFAULT_ACTION_SPACE.max_translation}] m per "
                             f"step, got {self.speed}")

    def start(self, rng: np.random.Generator) -> "ApproachDriftState":
        """A fresh drift for one episode, drawing from `rng`."""
        return ApproachDriftState(self, rng)


class ApproachDriftState:
    """The drift of one episode: `apply(action, observation)` -> (applied action, disturbed?).

    `observation['ee_target']` (4x4, the executor's commanded tcp pose) tells the height."""

    def __init__(self, settings: ApproachDrifts, rng: np.random.Generator) -> None:
        self.settings = settings
        self.start_z = float(rng.uniform(*settings.start_z))
        heading = float(rng.uniform(-np.pi, np.pi))
        self.offset = float(rng.uniform(*settings.offset)) * np.array([np.cos(heading), np.sin(heading)])
        self.turn = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(*settings.turn))
        # As many steps as the slower of the sideways move and the turn needs, both spread evenly over them.
        turn_steps = abs(self.turn) / DEFAULT_ACTION_SPACE.max_rotation
        self.steps = int(np.ceil(max(np.linalg.norm(self.offset) / settings.speed, turn_steps, 1.0)))
        self.remaining = -1  # -1: not started; then the steps left; 0: done (or never, past the first close)

    def apply(self, action: np.ndarray, observation: dict | None = None) -> tuple[np.ndarray, bool]:
        if self.remaining == -1:
            when = descent_below(action, observation, self.start_z, "ApproachDrifts")
            if when != WAITING:
                self.remaining = self.steps if when == STARTED else 0  # PAST: this episode does not drift
        if self.remaining <= 0:
            return action, False
        self.remaining -= 1
        applied = np.zeros(ACTION_DIM)
        applied[:2] = self.offset / self.steps
        applied[5] = self.turn / self.steps
        applied[6] = GRIPPER_OPEN
        return applied, True
