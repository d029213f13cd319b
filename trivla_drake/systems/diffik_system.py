"""`DifferentialIKSystem`: the OSQP differential IK as a Drake LeafSystem with a periodic update."""

from __future__ import annotations

import logging
import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from trivla_drake.robot.osqp_diffik import DiffIKParams, DiffIKStatus, OsqpDifferentialIK, pose_error
from trivla_drake.robot.panda_kinematics import PandaKinematics
from trivla_drake.systems.robot_base import base_pose_matrix

_log = logging.getLogger(__name__)
N_ARM = 7
# If the arm lags its commanded position by more than this [rad] (a collision, say), the
# integrator restarts from the measured position instead of winding up.
RESYNC_THRESHOLD = 0.3
STATUS_CODES = {DiffIKStatus.SOLVED: 0.0, DiffIKStatus.SOLVED_INACCURATE: 1.0, DiffIKStatus.SOLVER_FAILED: 2.0}
REJECTED_TARGET = 3.0


class DifferentialIKSystem(LeafSystem):
    """Turns an end-effector pose target into arm joint setpoints, one QP every `params.dt` seconds.

    Input `ee_target`: RigidTransform X_WT, pose of the Panda's `panda_hand_tcp` frame in the world [m].
    Input `robot_state`: 18-vector from the station's `panda.state`: q (7 arm [rad], 2 fingers [m]) then v
    [rad/s, m/s].
    Output `position_setpoint`: 7-vector of arm joint setpoints [rad], for `panda.position`.
    Output `status`: 1-vector, 0 solved, 1 solved inaccurately, 2 solver failed (held),
    3 target rejected (NaN/inf; held).
    Output `tracking_error`: 2-vector [distance [m], angle [rad]] between the measured hand (forward
    kinematics of the measured q) and `ee_target` at the last tick (NaN before the first tick, while
    the target is rejected, and always when `warn_tracking` is False). A warning is logged once when the
    distance stays above `tracking_warning_distance_m` for `tracking_warning_after_s` (an arm that does not
    follow its setpoints: a driver not connected, a blocked arm), and again after it has recovered and lost
    track anew. `warn_tracking=False` turns the check off (no forward kinematics, no warning): for harnesses
    whose hand is blocked on purpose (pressed on a block); the setpoints do not depend on it.

    The kinematics are the Panda's in its base frame B (`panda_link0`); `X_WB`, the base's pose in the
    world (identity by default), maps the world-frame target into it. The commanded position is integrated
    in the Context's discrete state (like Drake's DifferentialInverseKinematicsIntegrator) and starts from
    the measured position at initialisation. A target with NaN or infinity is rejected with a logged error
    naming the port, and the arm holds its commanded position.
    """

    def __init__(
        self,
        params: DiffIKParams | None = None,
        *,
        kinematics: PandaKinematics | None = None,
        X_WB: RigidTransform | None = None,
        tracking_warning_distance_m: float = 0.05,
        tracking_warning_after_s: float = 1.0,
        warn_tracking: bool = True,
    ):
        super().__init__()
        if not isinstance(warn_tracking, bool):
            raise ValueError(f"DifferentialIKSystem warn_tracking must be True or False, got {warn_tracking!r}")
        for name, value in (("tracking_warning_distance_m", tracking_warning_distance_m),
                            ("tracking_warning_after_s", tracking_warning_after_s)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                      and value > 0):
                raise ValueError(f"DifferentialIKSystem {name} must be a positive, finite number, got {value!r}")
        self._params = params or DiffIKParams()
        self._kinematics = kinematics or PandaKinematics()
        # The solver owns preallocated buffers and an OSQP workspace: scratch space, not state.
        # Each answer is a function of (q, target) alone (OsqpDifferentialIK restarts OSQP from the
        # same point every tick and polishes exactly), so Contexts sharing this system never interact.
        # Being shared scratch space, it is not thread-safe: threads simulating at once each build their own.
        self._solver = OsqpDifferentialIK(self._kinematics, self._params)
        X_WB_matrix = base_pose_matrix(X_WB, "X_WB")
        # Multiplying by the identity is exact, as the target has no NaN/inf (those are rejected).
        self._X_BW = np.eye(4) if X_WB_matrix is None else RigidTransform(X_WB_matrix).inverse().GetAsMatrix4()
        self._warning_distance = float(tracking_warning_distance_m)
        self._warning_after = float(tracking_warning_after_s)
        self._warn_tracking = warn_tracking
        self._target_port = self.DeclareAbstractInputPort("ee_target", AbstractValue.Make(RigidTransform()))
        self._state_port = self.DeclareVectorInputPort("robot_state", 2 * (N_ARM + 2))
        # Discrete state: [q_commanded (7), status (1)], and apart [distance, angle, far since [s] (NaN while
        # near), warned (0/1)] for the tracking check.
        self._state_index = self.DeclareDiscreteState(N_ARM + 1)
        self._tracking_index = self.DeclareDiscreteState(4)
        self.DeclarePeriodicDiscreteUpdateEvent(self._params.dt, 0.0, self._tick)
        self.DeclareInitializationDiscreteUpdateEvent(self._start_from_measured)
        # The outputs read the discrete state alone: no direct feedthrough from any input.
        state_only = {self.xd_ticket()}
        self.DeclareVectorOutputPort("position_setpoint", N_ARM, self._calc_setpoint, prerequisites_of_calc=state_only)
        self.DeclareVectorOutputPort("status", 1, self._calc_status, prerequisites_of_calc=state_only)
        self.DeclareVectorOutputPort("tracking_error", 2, self._calc_tracking_error, prerequisites_of_calc=state_only)

    def _start_from_measured(self, context, discrete_state):
        q = self._state_port.Eval(context)[:N_ARM]
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(np.append(q, 0.0))
        discrete_state.get_mutable_vector(self._tracking_index).SetFromVector([np.nan, np.nan, np.nan, 0.0])

    def _tick(self, context, discrete_state):
        stored = context.get_discrete_state(self._state_index).value()
        q_cmd = stored[:N_ARM]
        q_measured = self._state_port.Eval(context)[:N_ARM]
        if np.max(np.abs(q_cmd - q_measured)) > RESYNC_THRESHOLD:
            q_cmd = q_measured
        X_BTarget = self._X_BW @ self._target_port.Eval(context).GetAsMatrix4()
        # Problems are logged when they start (the status output says so every tick), not on every 10 ms tick.
        previous = stored[N_ARM]
        tracking = context.get_discrete_state(self._tracking_index).value()
        try:
            result = self._solver.solve(q_cmd, X_BTarget)
        except ValueError as error:
            if previous != REJECTED_TARGET:
                _log.error("DifferentialIKSystem input port 'ee_target' rejected at t = %.3f s: %s; holding position",
                           context.get_time(), error)
            next_state = np.append(q_cmd, REJECTED_TARGET)
            tracking = [np.nan, np.nan, np.nan, tracking[3]]
        else:
            status = STATUS_CODES[result.status]
            if status == STATUS_CODES[DiffIKStatus.SOLVER_FAILED] and previous != status:
                _log.warning("DifferentialIKSystem: the QP failed at t = %.3f s; holding position until it solves",
                             context.get_time())
            next_state = np.append(result.q_next, status)
            if self._warn_tracking:
                tracking = self._check_tracking(context.get_time(), q_measured, X_BTarget, tracking)
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(next_state)
        discrete_state.get_mutable_vector(self._tracking_index).SetFromVector(tracking)

    def _check_tracking(self, t: float, q_measured: np.ndarray, X_BTarget: np.ndarray, previous) -> list[float]:
        """The next tracking state [distance, angle, far since, warned], warning when the hand has stayed far."""
        error = pose_error(self._kinematics.pose(q_measured), X_BTarget)
        distance, angle = float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:]))
        far_since, warned = previous[2], previous[3]
        if distance <= self._warning_distance:
            return [distance, angle, np.nan, 0.0]
        if math.isnan(far_since):
            far_since = t
        if not warned and t - far_since >= self._warning_after - 1e-9:
            _log.warning("DifferentialIKSystem: the measured hand has stayed more than %.3f m from 'ee_target' for "
                         "%.2f s (now %.3f m at t = %.3f s): is the arm following 'position_setpoint' (a driver "
                         "connected, the arm not blocked)? See the output 'tracking_error'",
                         self._warning_distance, t - far_since, distance, t)
            warned = 1.0
        return [distance, angle, far_since, warned]

    def _calc_setpoint(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(self._state_index).value()[:N_ARM])

    def _calc_status(self, context, output: BasicVector):
        output.SetAtIndex(0, context.get_discrete_state(self._state_index).value()[N_ARM])

    def _calc_tracking_error(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(self._tracking_index).value()[:2])
