"""`HomeFirst`: a policy wrapper that, at the start of every task that does not start the episode, first brings
the tool-centre point back to the start posture's pose and only then hands over to the wrapped policy.

In a chain every task but the first starts where the one before it left the hand (by a drawer handle, above a
moved block, turned by a rotation); the clean demonstrations start from the start posture. Going home first makes
a later task start the way a first one does, with only the scene changed. The homing is scripted (no learning):
the hand rises straight up to the home height if it is below it, then moves and turns to the home pose along a
straight line, each step within the action bounds. The commanded pose gets there first: the diff-IK follows a
commanded path at the action's top speed up to some 13 cm behind, so the arm would still be moving fast (0.7-1.7
rad/s), often centimetres from home, when the policy takes over (an earlier version handed over then, and the
tasks after a prelude did worse than without it, research/prelude_reset/). So the wrapper then holds the commanded
pose until the measured tool-centre point is within `SETTLED_M` of home and the arm has all but stopped, as it is
at the start of an episode, or until its `max_steps` are spent (then the arm may still be turning slowly: 3 of 12
homings after a prelude, research/prelude_reset/). A task that starts the episode (simulated time 0: a single task,
or a chain's first) starts in the start posture already and is not homed. The hand opens, as it is at the start
posture, unless it is closed on something (the fingers stopped apart): a block held after a lift stays in the
hand. Its steps count against the task's step budget like any others.
"""

from __future__ import annotations

import numpy as np

from trivla_drake.systems.action_executor import GRIPPER_CLOSE, GRIPPER_OPEN, apply_action, delta_action, log_so3
from trivla_drake.tasks.scene import HOME_ARM_Q

# A hand within these of the home pose has arrived [m], [rad].
ARRIVED_M, ARRIVED_RAD = 0.005, 0.03
# Steps of one homing chunk; the longest homing the wrapper allows (36 Hz: 3 s).
CHUNK_STEPS, MAX_HOMING_STEPS = 12, 108
# Steps of one chunk that holds the commanded pose while the arm catches up.
SETTLE_STEPS = 3
# The policy takes over once the measured tool-centre point is this near the home position [m] and the arm's
# joint speeds (the state's entries 9 to 15) have this norm or less [rad/s].
SETTLED_M, SETTLED_SPEED = 0.01, 0.05
# Below the home height by more than this, the hand first rises straight up [m].
RISE_FIRST_M = 0.02
# A closed hand whose fingers stay further apart than this holds something [m] (a block: 0.045).
HOLDING_WIDTH_M = 0.01
# An open hand's fingers are this far apart or more [m] (fully open: 0.08).
OPEN_WIDTH_M = 0.075


def home_tcp_pose() -> np.ndarray:
    """The tool-centre point's pose (4x4, world) at the start posture `HOME_ARM_Q`."""
    import torch

    from trivla_drake.nn.panda_tcp import PandaTcpFeatures

    with torch.no_grad():
        return PandaTcpFeatures().pose(torch.tensor(HOME_ARM_Q[None], dtype=torch.float64))[0].double().numpy()


def homing_actions(commanded: np.ndarray, home: np.ndarray, gripper: float, steps: int) -> np.ndarray:
    """Up to `steps` actions (k, 7) taking the commanded pose `commanded` towards `home` (rising first when
    well below it), stopping once arrived; (0, 7) when it already is."""
    rows, X = [], np.array(commanded, dtype=float)
    for _ in range(steps):
        if _arrived(X, home):
            break
        goal = home
        if X[2, 3] < home[2, 3] - RISE_FIRST_M:  # straight up first: away from handles and blocks
            goal = X.copy()
            goal[2, 3] = home[2, 3]
        action = delta_action(X, goal, gripper)
        rows.append(action)
        X, _ = apply_action(X, action)
    return np.array(rows, dtype=float).reshape(-1, 7)


def homing_gripper(observation: dict) -> float:
    """Open (+1), unless the hand is closed on something (-1): commanded closed with the measured fingers
    (the state's entries 7 and 8, [m] each) further apart than `HOLDING_WIDTH_M`."""
    return GRIPPER_CLOSE if observation["gripper_command"] <= 0 and _width(observation) > HOLDING_WIDTH_M else GRIPPER_OPEN


def _width(observation: dict) -> float:
    return float(observation["state"][7] + observation["state"][8])


def _arrived(X: np.ndarray, home: np.ndarray) -> bool:
    return (np.linalg.norm(X[:3, 3] - home[:3, 3]) < ARRIVED_M
            and np.linalg.norm(log_so3(home[:3, :3] @ X[:3, :3].T)) < ARRIVED_RAD)


class Homing:
    """The scripted homing itself, one task's worth at a time: `start()` it, then `rows(observation)` gives the
    next actions (k, 7) until it is over (None): the commanded pose home and the measured arm settled there (with
    `settle`), or `max_steps` spent. A task at simulated time 0 is not homed (with `settle`)."""

    def __init__(self, *, max_steps: int = MAX_HOMING_STEPS, settle: bool = True):
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps must be an integer >= 1 (control steps), got {max_steps!r}")
        self.max_steps = max_steps
        # False: the first version (research/home_first/ was made with it, up to commit d85a985; it did worse
        # than no homing at all), kept for the diagnostics of research/prelude_reset/: it homes at the episode's
        # start too, and hands over once the commanded pose is home and the fingers are open, the arm still
        # catching up.
        self.settle = settle
        self._home = home_tcp_pose()
        self._left = 0

    def start(self) -> None:
        self._left = self.max_steps

    def rows(self, observation: dict) -> np.ndarray | None:
        if self.settle and self._left == self.max_steps and observation["time"] == 0.0:
            self._left = 0  # the episode's start: the arm is in its start posture already
        if self._left <= 0:
            return None
        gripper, steps = homing_gripper(observation), min(CHUNK_STEPS, self._left)
        rows = homing_actions(observation["ee_target"], self._home, gripper, steps)
        if not len(rows) and self.settle and not self._settled(observation, gripper):
            rows = np.tile(np.r_[np.zeros(6), gripper], (min(SETTLE_STEPS, steps), 1))  # wait for the arm
        elif not len(rows) and not self.settle and not _fingers_ready(observation, gripper):
            rows = np.tile(np.r_[np.zeros(6), GRIPPER_OPEN], (steps, 1))  # the first version: the fingers only
        self._left = self._left - len(rows) if len(rows) else 0
        return rows if len(rows) else None

    def _settled(self, observation: dict, gripper: float) -> bool:
        """The measured arm is at home and all but still, and the fingers are open unless they hold a block."""
        near = np.linalg.norm(observation["tcp_pose"][:3, 3] - self._home[:3, 3]) < SETTLED_M
        still = np.linalg.norm(observation["state"][9:16]) <= SETTLED_SPEED
        return near and still and _fingers_ready(observation, gripper)


def _fingers_ready(observation: dict, gripper: float) -> bool:
    """Open, unless they are to stay closed on a block."""
    return gripper != GRIPPER_OPEN or _width(observation) >= OPEN_WIDTH_M


class HomeFirst:
    """Wraps a Policy (reset / act): each reset starts a homing phase (`Homing`: at most `max_steps` control
    steps; none for a task at simulated time 0) that ends when the commanded pose has reached the start
    posture's and the measured arm has settled there; then `policy` acts."""

    privileged = False

    def __init__(self, policy, *, max_steps: int = MAX_HOMING_STEPS, settle: bool = True):
        if getattr(policy, "privileged", False):
            raise ValueError("HomeFirst wraps learned policies; the oracle plans from wherever the hand is")
        self._homing = Homing(max_steps=max_steps, settle=settle)
        self.policy = policy
        self.name = f"{policy.name}+home"
        self.uses_images = policy.uses_images

    @property
    def max_steps(self) -> int:
        return self._homing.max_steps

    def reset(self, instruction: str, seed: int) -> None:
        self._homing.start()
        self.policy.reset(instruction, seed)

    def act(self, observation: dict) -> np.ndarray:
        rows = self._homing.rows(observation)
        return self.policy.act(observation) if rows is None else rows
