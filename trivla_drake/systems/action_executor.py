"""The policy-facing action space and `ActionExecutor`, its adapter onto the station's ports.

This module is the one place the action is defined; the dataset, the oracle, the random policy
and learned policies all use it.

Action (7 floats, one per control step, applied at `control_rate_hz`, default 36 Hz, the paper's
control frequency):

    [dx, dy, dz, drx, dry, drz, gripper]

- dx, dy, dz [m]: translation of the commanded tool-centre point (`panda_hand_tcp`) in the
  world frame (x away from the robot, y to its left, z up).
- drx, dry, drz [rad]: rotation increment as an axis-angle vector in world axes, applied to the
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
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from trivla_drake.station.panda_driver import MAX_GRIPPER_WIDTH

ACTION_NAMES = ("dx", "dy", "dz", "drx", "dry", "drz", "gripper")
ACTION_DIM = 7
GRIPPER_OPEN, GRIPPER_CLOSE = 1.0, -1.0
OPEN_WIDTH = MAX_GRIPPER_WIDTH  # [m] commanded finger distance for an open hand (fully open)
CLOSED_WIDTH = 0.0  # [m] commanded finger distance for a closed hand


@dataclass(frozen=True)
class ActionSpace:
    """Settings of the relative end-effector action; every default is what the datasets use."""

    # Control rate: one action per 1/control_rate_hz seconds [Hz] (the paper's 36 Hz).
    control_rate_hz: float = 36.0
    # Largest translation per step and component [m].
    max_translation: float = 0.01
    # Largest rotation increment per step and component [rad].
    max_rotation: float = 0.05
    # Box the commanded tcp position is kept in [m] (world frame).
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


def exp_so3(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis-angle vector (Rodrigues)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (inverse of `exp_so3`, angle in [0, pi])."""
    angle_axis = RotationMatrix(_orthonormalize(R)).ToAngleAxis()
    return angle_axis.angle() * np.asarray(angle_axis.axis())


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(R)
    result = u @ vt
    if np.linalg.det(result) < 0:
        u[:, -1] *= -1
        result = u @ vt
    return result


def apply_action(
    X_target: np.ndarray, action: np.ndarray, space: ActionSpace = DEFAULT_ACTION_SPACE
) -> tuple[np.ndarray, float]:
    """One control step: (commanded 4x4 tcp pose, action) -> (next commanded pose, gripper width [m])."""
    action = check_action(action)
    clipped = np.clip(action, space.low, space.high)
    X_next = np.eye(4)
    X_next[:3, 3] = np.clip(
        X_target[:3, 3] + clipped[:3], np.asarray(space.workspace_low), np.asarray(space.workspace_high)
    )
    X_next[:3, :3] = _orthonormalize(exp_so3(clipped[3:6]) @ X_target[:3, :3])
    width = OPEN_WIDTH if clipped[6] > 0.0 else CLOSED_WIDTH
    return X_next, width


def delta_action(
    X_from: np.ndarray, X_to: np.ndarray, gripper: float, space: ActionSpace = DEFAULT_ACTION_SPACE
) -> np.ndarray:
    """The action moving the commanded pose X_from towards X_to, each part clipped to the bounds."""
    action = np.empty(ACTION_DIM)
    action[:3] = X_to[:3, 3] - X_from[:3, 3]
    action[3:6] = log_so3(X_to[:3, :3] @ X_from[:3, :3].T)
    action[6] = gripper
    return np.clip(action, space.low, space.high)


class ActionExecutor(LeafSystem):
    """Integrates relative end-effector actions into the diff-IK's `ee_target` at the control rate.

    Input `action`: 7-vector (see the module docstring), read every 1/control_rate_hz seconds.
    Input `robot_state`: 18-vector from the station's `panda.state`, read at initialisation only.
    Output `ee_target`: RigidTransform of `panda_hand_tcp` in the world, for DifferentialIKSystem.
    Output `gripper_width`: 1-vector [m], for the station's `panda.gripper_width`.
    Output `commanded_pose`: 12-vector [p (3); R (9, row-major)] of the commanded tcp pose.

    Discrete state [p (3), R (9, row-major), width (1)] starts at the measured tcp pose (forward
    kinematics of the arm at initialisation) and the measured finger distance. The Panda base is
    the world origin (as in the station).
    """

    def __init__(self, space: ActionSpace = DEFAULT_ACTION_SPACE, *, kinematics=None):
        super().__init__()
        from trivla_drake.robot.panda_kinematics import PandaKinematics

        self._space = space
        self._kinematics = kinematics or PandaKinematics()
        self._action_port = self.DeclareVectorInputPort("action", ACTION_DIM)
        self._state_port = self.DeclareVectorInputPort("robot_state", 18)
        self._state_index = self.DeclareDiscreteState(13)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialise)
        self.DeclarePeriodicDiscreteUpdateEvent(space.dt, 0.0, self._step)
        self.DeclareAbstractOutputPort(
            "ee_target", lambda: AbstractValue.Make(RigidTransform()), self._calc_target
        )
        self.DeclareVectorOutputPort("gripper_width", 1, self._calc_width)
        self.DeclareVectorOutputPort("commanded_pose", 12, self._calc_pose)

    @property
    def action_space(self) -> ActionSpace:
        return self._space

    def _initialise(self, context, discrete_state):
        robot_state = self._state_port.Eval(context)
        X = self._kinematics.ee_pose(robot_state[:7])
        width = float(np.clip(robot_state[7] + robot_state[8], CLOSED_WIDTH, OPEN_WIDTH))
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(_pack(X, width))

    def _step(self, context, discrete_state):
        X, _ = _unpack(context.get_discrete_state(self._state_index).value())
        X_next, width = apply_action(X, self._action_port.Eval(context), self._space)
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(_pack(X_next, width))

    def _calc_target(self, context, output):
        X, _ = _unpack(context.get_discrete_state(self._state_index).value())
        output.set_value(RigidTransform(X))

    def _calc_width(self, context, output: BasicVector):
        output.SetAtIndex(0, context.get_discrete_state(self._state_index).value()[12])

    def _calc_pose(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(self._state_index).value()[:12])

    def commanded_pose(self, context) -> np.ndarray:
        """The commanded tcp pose (4x4) held in `context` (this system's context)."""
        return _unpack(context.get_discrete_state(self._state_index).value())[0]


def _pack(X: np.ndarray, width: float) -> np.ndarray:
    return np.concatenate([X[:3, 3], X[:3, :3].reshape(-1), [width]])


def _unpack(vector: np.ndarray) -> tuple[np.ndarray, float]:
    X = np.eye(4)
    X[:3, 3] = vector[:3]
    X[:3, :3] = np.asarray(vector[3:12]).reshape(3, 3)
    return X, float(vector[12])
