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
    GRIPPER_CLOSE,
    GRIPPER_OPEN,
    ActionSpace,
    log_so3,
)
from trivla_drake.tasks import motions
from trivla_drake.tasks.motions import Waypoint
from trivla_drake.tasks.suite import get_task


# Longest time one waypoint leg may take before the oracle moves on [s].
MAX_LEG_S = 8.0
# With `turn_first`, how far the hand may be turned off a `Waypoint.turn_first` leg's pose before the
# expert stops moving towards it and only turns [rad] (about 6 degrees).
TURN_FIRST_RAD = 0.1
# With `align_first`, how far the commanded tcp may be sideways (in x-y) off a `Waypoint.turn_first` leg's
# target before the expert stops going down and only moves across and turns [m].
ALIGN_FIRST_M = 0.004
# With `resume_descent`, a hand found below the leg above a grasp by more than RESUME_BELOW_M, within
# RESUME_RADIUS_M sideways of the grasp and at least RESUME_ABOVE_M above it goes on with the leg down [m].
RESUME_BELOW_M = 0.01
RESUME_RADIUS_M = 0.04
RESUME_ABOVE_M = 0.03


class OraclePolicy:
    """Scripted expert for every task in the suite (see `trivla_drake.eval.policies.Policy`)."""

    name = "oracle"
    uses_images = False
    privileged = True

    def __init__(self, action_space: ActionSpace = DEFAULT_ACTION_SPACE, detours: int = 0,
                 turn_first: bool = False, regrasp: bool = False, align_first: bool = False,
                 resume_descent: bool = False):
        """`detours`: before its task, the expert visits this many places just above blocks the
        instruction does not name (motions.detours; drawn from the reset's seed). 0: none.
        `turn_first`: on the legs down to a grasp (`Waypoint.turn_first`), hold the position while the
        hand is more than TURN_FIRST_RAD off the leg's yaw, e.g. after a yaw twist
        (eval/action_noise.py); in undisturbed episodes the hand is already turned right there, so
        it changes nothing.
        `align_first`: on those legs, stop going down while the commanded tcp is more than ALIGN_FIRST_M
        sideways or TURN_FIRST_RAD turned off the leg's target, and move across and turn until it is not,
        e.g. after an approach drift (eval/approach_drifts.py); undisturbed, the hand comes down
        straight above its target, so it changes nothing.
        `regrasp`: when the hand is commanded closed although the expert's current leg has it open
        (a missed grasp forced on it, eval/missed_grasps.py), plan again from the scene as it is:
        open, rise, then the task's plan (which grasps again). The expert never does that itself,
        so without a disturbance it changes nothing.
        `resume_descent`: which of the two legs to a grasp (to above it, then the `Waypoint.turn_first` leg
        down) applies is decided from where the commanded hand is now, at every step, for hands that
        someone else drove (eval/policy_takeover.py, which also calls `replan()` when it hands back). A
        hand in the funnel above the grasp (lower than the leg above by RESUME_BELOW_M, within
        RESUME_RADIUS_M sideways, at least RESUME_ABOVE_M above the grasp) goes on with the leg down;
        with `align_first` it first moves across and turns at that height. A hand on the leg down
        that is neither aligned (ALIGN_FIRST_M, TURN_FIRST_RAD) nor in that funnel goes back to the
        leg above: it rises (and moves across) until it is in the funnel. Undisturbed, the hand
        reaches the leg above from above and comes down aligned, so it changes nothing."""
        if isinstance(detours, bool) or not isinstance(detours, (int, np.integer)) or detours < 0:
            raise ValueError(f"detours must be an integer >= 0, got {detours!r}")
        self._space = action_space
        self._detours = int(detours)
        self._turn_first = bool(turn_first)
        self._regrasp = bool(regrasp)
        self._align_first = bool(align_first)
        self._resume_descent = bool(resume_descent)
        self._replan = False
        self._rng = np.random.default_rng(0)
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
        self._rng = np.random.default_rng(seed)

    def replan(self) -> None:
        """The next `act` plans the task again from the scene as it is then (no retreat, no detours): for
        an expert taking over a hand someone else drove, e.g. after a learned policy moved a block."""
        self._replan = True

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
            self._plan = motions.retreat(scene, closed) + self._detour_plan(scene, instance) \
                + get_task(instance.task).plan(instance.params, scene)
        elif self._replan:
            self._plan = get_task(instance.task).plan(instance.params, scene)
            self._index, self._waited, self._leg_steps = 0, 0, 0
        elif self._regrasp and closed and self._gripper > 0.0:
            # Closed by someone else: whatever it grasped or not, open, rise and go on from the scene as it is.
            self._plan = motions.retreat(scene, closed) + get_task(instance.task).plan(instance.params, scene)
            self._index, self._waited, self._leg_steps = 0, 0, 0
        self._replan = False
        if self._resume_descent:
            self._choose_grasp_leg(X_cmd)
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

    def _choose_grasp_leg(self, X_cmd: np.ndarray) -> None:
        """`resume_descent`: the leg above a grasp or the leg down to it, from where the hand is now."""
        on_down = self._plan[self._index].turn_first if self._index < len(self._plan) else False
        above_index = self._index - 1 if on_down else self._index
        if above_index < 0 or above_index + 1 >= len(self._plan) or not self._plan[above_index + 1].turn_first:
            return
        above, down = self._plan[above_index].pose, self._plan[above_index + 1].pose
        p = X_cmd[:3, 3]
        across = float(np.linalg.norm(p[:2] - down[:2, 3]))
        in_funnel = down[2, 3] + RESUME_ABOVE_M < p[2] < above[2, 3] - RESUME_BELOW_M and across < RESUME_RADIUS_M
        if not on_down and in_funnel:
            self._index, self._waited, self._leg_steps = above_index + 1, 0, 0
        elif on_down and not in_funnel:
            turned = float(np.linalg.norm(log_so3(down[:3, :3] @ X_cmd[:3, :3].T)))
            if across > ALIGN_FIRST_M or turned > TURN_FIRST_RAD:
                self._index, self._waited, self._leg_steps = above_index, 0, 0

    def _detour_plan(self, scene, instance) -> list[Waypoint]:
        if not self._detours:
            return []
        named = instance.params[0] if instance.params and instance.params[0] in scene.blocks else None
        # After `retreat` the hand is open unless it carries a block.
        gripper = GRIPPER_CLOSE if scene.held_block() is not None else GRIPPER_OPEN
        return motions.detours(scene, named, self._rng, self._detours, gripper)

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
        if self._turn_first and wp.turn_first and angle > TURN_FIRST_RAD:
            action[:3] = 0.0
        elif self._align_first and wp.turn_first and d[2] < 0.0:
            across = float(np.linalg.norm(d[:2]))
            if across > ALIGN_FIRST_M or angle > TURN_FIRST_RAD:  # across and turn only, at this height
                action[:3] = 0.0
                action[:2] = d[:2] if across <= max_step else d[:2] * (max_step / across)
        action[3:6] = r if angle <= max_turn else r * (max_turn / angle)
        action[6] = wp.gripper
        return action, at_target
