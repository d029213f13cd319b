"""Missed grasps for demonstration collection: the expert's first grasp is made to miss, then it retries.

A learned policy's grasp sometimes misses: it closes its hand 2-3 cm off the block, or turned
40 degrees off its faces, and the fingers meet nothing or the block's top (results/grasp_yaw). In
clean demonstrations every grasp holds, so nothing shows what to do with a hand closed on nothing,
and the policy carries the empty hand on. `MissedGrasps` disturbs the expert's first grasp so that
it misses, and the expert (with `OraclePolicy(regrasp=True)`) recovers: it opens the hand, rises and
grasps again from the scene as it is then.

Once per episode, the first time the commanded tool-centre point comes down with the gripper open
below a height drawn from `start_z` (before the gripper first closes), the applied actions are
replaced: the commanded tcp goes down to `close_z` at a point `offset` metres (drawn, either side)
across the fingers' closing direction from where it was heading (plus up to `along` metres along
it), turning `turn` radians about the vertical (drawn, either sign) on the way, and then the gripper
is commanded closed for `close_steps` steps. Beside the block, the fingers close on air; turned, they
land on its top or its corners, as a learned policy's missed grasps do. The recorded
actions stay the expert's, and every replaced step is marked disturbed (`Trajectory.perturbed`), so
training uses the expert's answer to those frames and masks the rest of their chunks (see
`trivla_drake.data.samples`). The expert sees its hand closed against its plan and re-plans: open,
rise, grasp again. Those frames are the labels this data set is for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trivla_drake.eval.action_noise import PAST, STARTED, descent_below
from trivla_drake.systems.action_executor import ACTION_DIM, DEFAULT_ACTION_SPACE, GRIPPER_CLOSE, GRIPPER_OPEN


@dataclass(frozen=True)
class MissedGrasps:
    """Settings of the missed grasp (see the module docstring)."""

    # The miss starts the first time the commanded tcp, descending with the gripper open and before
    # the gripper first closes, is below a height drawn uniformly from this range [m].
    start_z: tuple[float, float] = (0.07, 0.11)
    # Distance of the missed grasp from where the expert was heading, across the fingers' closing
    # direction [m], drawn uniformly; the side is drawn too.
    offset: tuple[float, float] = (0.03, 0.045)
    # Largest distance along the closing direction [m] (drawn uniformly in +-along).
    along: float = 0.01
    # Turn of the hand about the vertical on the way down [rad], drawn uniformly; the sign is drawn too.
    turn: tuple[float, float] = (0.0, 0.75)
    # Height the commanded tcp goes down to before closing [m] (the expert grasps at about 0.025).
    close_z: float = 0.025
    # Speed of the commanded tcp on the way down [m per step] (the expert's 0.12 m/s at 36 Hz).
    speed: float = 0.0033
    # Steps the gripper is commanded closed before the expert gets the hand back (0.5 s at 36 Hz).
    close_steps: int = 18

    def __post_init__(self) -> None:
        if not 0.0 < self.start_z[0] <= self.start_z[1]:
            raise ValueError(f"missed grasp start_z range must be 0 < low <= high, got {self.start_z}")
        if not 0.0 <= self.offset[0] <= self.offset[1]:
            raise ValueError(f"missed grasp offset range must be 0 <= low <= high, got {self.offset}")
        if self.along < 0.0:
            raise ValueError(f"missed grasp along must be >= 0, got {self.along}")
        if not 0.0 <= self.turn[0] <= self.turn[1] <= np.pi / 4:
            raise ValueError(f"missed grasp turn range must be 0 <= low <= high <= pi/4, got {self.turn}")
        if not 0.0 < self.close_z < self.start_z[0]:
            raise ValueError(f"missed grasp close_z must be in (0, start_z low), got {self.close_z}")
        if not 0.0 < self.speed <= 0.01:
            raise ValueError(f"missed grasp speed must be in (0, 0.01] m per step, got {self.speed}")
        if self.close_steps < 1:
            raise ValueError(f"missed grasp close_steps must be >= 1, got {self.close_steps}")

    def start(self, rng: np.random.Generator) -> "MissedGraspState":
        """A fresh missed grasp for one episode, drawing from `rng`."""
        return MissedGraspState(self, rng)


class MissedGraspState:
    """The missed grasp of one episode: `apply(action, observation)` -> (applied action, disturbed?).

    `observation['ee_target']` (4x4, the executor's commanded tcp pose) tells where the hand is."""

    # Phases: waiting for the descent, going down to the missed grasp, closing, done.
    WAITING, DESCENDING, CLOSING, DONE = range(4)

    def __init__(self, settings: MissedGrasps, rng: np.random.Generator) -> None:
        self.settings = settings
        self.start_z = float(rng.uniform(*settings.start_z))
        # In the hand's frame: x across the fingers' closing direction, y along it.
        self.offset_in_hand = np.array([float(rng.choice([-1.0, 1.0])) * float(rng.uniform(*settings.offset)),
                                        float(rng.uniform(-settings.along, settings.along))])
        self.turn = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(*settings.turn))
        self.phase = self.WAITING
        self.target: np.ndarray | None = None  # where the commanded tcp closes [m]
        self.turned = 0.0  # [rad] so far
        self.closing_left = settings.close_steps

    def apply(self, action: np.ndarray, observation: dict | None = None) -> tuple[np.ndarray, bool]:
        if self.phase == self.WAITING:
            when = descent_below(action, observation, self.start_z, "MissedGrasps")
            if when == PAST:
                self.phase = self.DONE  # past the first grasp: this episode's grasp is not missed
                return action, False
            if when == STARTED:
                X = self._commanded(observation)
                self.phase = self.DESCENDING
                offset = X[:2, :2] @ self.offset_in_hand  # the hand's x and y axes, pointing down, are horizontal
                self.target = np.array([X[0, 3] + offset[0], X[1, 3] + offset[1], self.settings.close_z])
        if self.phase == self.DESCENDING:
            X = self._commanded(observation)
            applied = np.zeros(ACTION_DIM)
            step = self.target - X[:3, 3]
            distance = float(np.linalg.norm(step))
            applied[:3] = step if distance <= self.settings.speed else step * (self.settings.speed / distance)
            steps_left = max(distance / self.settings.speed, 1.0)
            limit = DEFAULT_ACTION_SPACE.max_rotation  # what the executor applies at most
            applied[5] = float(np.clip((self.turn - self.turned) / steps_left, -limit, limit))
            self.turned += applied[5]
            applied[6] = GRIPPER_OPEN
            if distance <= self.settings.speed:
                self.phase = self.CLOSING
            return applied, True
        if self.phase == self.CLOSING:
            self.closing_left -= 1
            if self.closing_left <= 0:
                self.phase = self.DONE
            applied = np.zeros(ACTION_DIM)
            applied[6] = GRIPPER_CLOSE
            return applied, True
        return action, False

    @staticmethod
    def _commanded(observation: dict | None) -> np.ndarray:
        if observation is None or "ee_target" not in observation:
            raise ValueError("MissedGrasps needs observation['ee_target'] (the commanded tcp pose)")
        return np.asarray(observation["ee_target"])
