"""The scripted expert: follows a task's waypoint plan through the policy-facing action space.

It reads the simulator's ground truth (the observation's `privileged` entry, which the episode
runner adds only for policies with `privileged = True`) to plan, and acts exactly like a learned
policy would: one relative end-effector action per control step, through the diff-IK.
"""

from __future__ import annotations

import numpy as np

from trivla_drake.systems.action_executor import (
    ACTION_DIM,
    DEFAULT_ACTION_SPACE,
    GRIPPER_OPEN,
    ActionSpace,
    log_so3,
)
from trivla_drake.tasks import motions
from trivla_drake.tasks.motions import Waypoint
from trivla_drake.tasks.suite import get_task


# Longest time one waypoint leg may take before the oracle moves on [s].
MAX_LEG_S = 8.0


class OraclePolicy:
    """Scripted expert for every task in the suite (see `trivla_drake.eval.policies.Policy`)."""

    name = "oracle"
    uses_images = False
    privileged = True

    def __init__(self, action_space: ActionSpace = DEFAULT_ACTION_SPACE):
        self._space = action_space
        self._plan: list[Waypoint] | None = None
        self._index = 0
        self._waited = 0
        self._leg_steps = 0
        self._gripper = GRIPPER_OPEN

    def reset(self, instruction: str, seed: int) -> None:
        """Forget the previous plan; the next `act` plans from the ground truth."""
        self._plan = None
        self._index = 0
        self._waited = 0
        self._leg_steps = 0

    @property
    def plan(self) -> list[Waypoint] | None:
        """The current episode's waypoints (after the first `act`)."""
        return self._plan

    def act(self, observation: dict) -> np.ndarray:
        """The next action (7,) towards the current waypoint."""
        privileged = observation.get("privileged")
        if privileged is None:
            raise ValueError("OraclePolicy needs observation['privileged'] (scene and task ground truth)")
        scene, instance = privileged["scene"], privileged["task"]
        X_cmd = np.asarray(observation["ee_target"])
        closed = float(observation.get("gripper_command", GRIPPER_OPEN)) <= 0.0
        if self._plan is None:
            self._plan = motions.retreat(scene, closed) + get_task(instance.task).plan(instance.params, scene)
        dt = self._space.dt
        while self._index < len(self._plan):
            wp = self._plan[self._index]
            self._gripper = wp.gripper
            action, at_target = self._toward(X_cmd, wp)
            self._leg_steps += 1
            # A leg whose target the executor cannot reach (outside its workspace) ends after a while.
            stuck = self._leg_steps * dt > MAX_LEG_S
            if not at_target and not stuck:
                self._waited = 0
                return action
            self._waited += 1
            elapsed = self._waited * dt
            error = np.linalg.norm(scene.tcp[:3, 3] - wp.pose[:3, 3])
            done = (error <= wp.tolerance and elapsed >= wp.settle_s) or elapsed >= wp.settle_s + wp.timeout_s
            if done or stuck:
                self._index += 1
                self._waited = 0
                self._leg_steps = 0
                continue
            return action
        hold = np.zeros(ACTION_DIM)
        hold[6] = self._gripper
        return hold

    def _toward(self, X_cmd: np.ndarray, wp: Waypoint) -> tuple[np.ndarray, bool]:
        """A step of at most the waypoint's speeds towards its pose; and whether X_cmd is there."""
        dt = self._space.dt
        action = np.zeros(ACTION_DIM)
        d = wp.pose[:3, 3] - X_cmd[:3, 3]
        r = log_so3(wp.pose[:3, :3] @ X_cmd[:3, :3].T)
        distance, angle = float(np.linalg.norm(d)), float(np.linalg.norm(r))
        at_target = distance < 1e-6 and angle < 1e-6
        max_step = min(wp.speed * dt, self._space.max_translation)
        max_turn = min(wp.angular_speed * dt, self._space.max_rotation)
        action[:3] = d if distance <= max_step else d * (max_step / distance)
        action[3:6] = r if angle <= max_turn else r * (max_turn / angle)
        action[6] = wp.gripper
        return action, at_target
