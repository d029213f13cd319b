"""`DifferentialIKSystem`: the OSQP differential IK as a Drake LeafSystem with a periodic update."""

from __future__ import annotations

import logging

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from trivla_drake.robot.osqp_diffik import DiffIKParams, DiffIKStatus, OsqpDifferentialIK
from trivla_drake.robot.panda_kinematics import PandaKinematics

_log = logging.getLogger(__name__)
N_ARM = 7
# If the arm lags its commanded position by more than this [rad] (a collision, say), the
# integrator restarts from the measured position instead of winding up.
RESYNC_THRESHOLD = 0.3
STATUS_CODES = {DiffIKStatus.SOLVED: 0.0, DiffIKStatus.SOLVED_INACCURATE: 1.0, DiffIKStatus.SOLVER_FAILED: 2.0}
REJECTED_TARGET = 3.0


class DifferentialIKSystem(LeafSystem):
    """Turns an end-effector pose target into arm joint setpoints, one QP every `params.dt` seconds.

    Input `ee_target`: RigidTransform, pose of the Panda's `panda_hand_tcp` frame in the world [m].
    Input `robot_state`: 18-vector from the station's `panda.state`: q (7 arm [rad], 2 fingers [m]) then v
    [rad/s, m/s].
    Output `position_setpoint`: 7-vector of arm joint setpoints [rad], for `panda.position`.
    Output `status`: 1-vector, 0 solved, 1 solved inaccurately, 2 solver failed (held),
    3 target rejected (NaN/inf; held).

    The commanded position is integrated in the Context's discrete state (like Drake's
    DifferentialInverseKinematicsIntegrator) and starts from the measured position at
    initialisation. A target with NaN or infinity is rejected with a logged error naming the port,
    and the arm holds its commanded position.
    """

    def __init__(
        self,
        params: DiffIKParams | None = None,
        *,
        kinematics: PandaKinematics | None = None,
        X_WBase: RigidTransform | None = None,
    ):
        super().__init__()
        self._params = params or DiffIKParams()
        # The solver owns preallocated buffers and an OSQP workspace: scratch space, not state.
        # Each answer is a function of (q, target) alone (OsqpDifferentialIK restarts OSQP from the
        # same point every tick and polishes exactly), so Contexts sharing this system never interact.
        # Being shared scratch space, it is not thread-safe: threads simulating at once each build their own.
        self._solver = OsqpDifferentialIK(kinematics or PandaKinematics(), self._params)
        self._X_BaseW = (X_WBase or RigidTransform()).inverse().GetAsMatrix4()
        self._target_port = self.DeclareAbstractInputPort("ee_target", AbstractValue.Make(RigidTransform()))
        self._state_port = self.DeclareVectorInputPort("robot_state", 2 * (N_ARM + 2))
        # Discrete state: [q_commanded (7), status (1)].
        self._state_index = self.DeclareDiscreteState(N_ARM + 1)
        self.DeclarePeriodicDiscreteUpdateEvent(self._params.dt, 0.0, self._tick)
        self.DeclareInitializationDiscreteUpdateEvent(self._start_from_measured)
        # The outputs read the discrete state alone: no direct feedthrough from any input.
        state_only = {self.xd_ticket()}
        self.DeclareVectorOutputPort("position_setpoint", N_ARM, self._calc_setpoint, prerequisites_of_calc=state_only)
        self.DeclareVectorOutputPort("status", 1, self._calc_status, prerequisites_of_calc=state_only)

    def _start_from_measured(self, context, discrete_state):
        q = self._state_port.Eval(context)[:N_ARM]
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(np.append(q, 0.0))

    def _tick(self, context, discrete_state):
        stored = context.get_discrete_state(self._state_index).value()
        q_cmd = stored[:N_ARM]
        q_measured = self._state_port.Eval(context)[:N_ARM]
        if np.max(np.abs(q_cmd - q_measured)) > RESYNC_THRESHOLD:
            q_cmd = q_measured
        X_WTarget = self._target_port.Eval(context).GetAsMatrix4()
        # Problems are logged when they start (the status output says so every tick), not on every 10 ms tick.
        previous = stored[N_ARM]
        try:
            result = self._solver.solve(q_cmd, self._X_BaseW @ X_WTarget)
        except ValueError as error:
            if previous != REJECTED_TARGET:
                _log.error("DifferentialIKSystem input port 'ee_target' rejected at t = %.3f s: %s; holding position",
                           context.get_time(), error)
            next_state = np.append(q_cmd, REJECTED_TARGET)
        else:
            status = STATUS_CODES[result.status]
            if status == STATUS_CODES[DiffIKStatus.SOLVER_FAILED] and previous != status:
                _log.warning("DifferentialIKSystem: the QP failed at t = %.3f s; holding position until it solves",
                             context.get_time())
            next_state = np.append(result.q_next, status)
        discrete_state.get_mutable_vector(self._state_index).SetFromVector(next_state)

    def _calc_setpoint(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(self._state_index).value()[:N_ARM])

    def _calc_status(self, context, output: BasicVector):
        output.SetAtIndex(0, context.get_discrete_state(self._state_index).value()[N_ARM])
