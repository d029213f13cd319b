"""`ActionExecutor`: the policy-facing action (`trivla_drake.action`, which also defines the bounds and
the commanded-pose semantics it implements) applied onto the station's ports."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

# The action's definition, re-exported: importers of this module keep finding it here.
from trivla_drake.action import (  # noqa: F401
    ACTION_DIM,
    ACTION_HIGH,
    ACTION_LOW,
    ACTION_NAMES,
    DEFAULT_ACTION_SPACE,
    GRIPPER_CLOSE,
    GRIPPER_OPEN,
    ActionSpace,
    check_action,
)
from trivla_drake.station.panda_driver import MAX_GRIPPER_WIDTH

OPEN_WIDTH = MAX_GRIPPER_WIDTH  # [m] commanded finger distance for an open hand (fully open)
CLOSED_WIDTH = 0.0  # [m] commanded finger distance for a closed hand


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
    Input `robot_state`: 18-vector from the station's `panda.state` (q: 7 arm [rad], 2 fingers [m]; then v
    [rad/s, m/s]), read at initialisation only.
    Output `ee_target`: RigidTransform of `panda_hand_tcp` in the world [m], for DifferentialIKSystem.
    Output `gripper_width`: 1-vector [m], for the station's `panda.gripper_width`.
    Output `commanded_pose`: 12-vector [p (3) [m]; R (9, row-major, unitless)] of the commanded tcp pose
    in the world.

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
        # The outputs read the discrete state alone: no direct feedthrough from any input.
        state_only = {self.xd_ticket()}
        self.DeclareAbstractOutputPort(
            "ee_target", lambda: AbstractValue.Make(RigidTransform()), self._calc_target,
            prerequisites_of_calc=state_only,
        )
        self.DeclareVectorOutputPort("gripper_width", 1, self._calc_width, prerequisites_of_calc=state_only)
        self.DeclareVectorOutputPort("commanded_pose", 12, self._calc_pose, prerequisites_of_calc=state_only)

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
