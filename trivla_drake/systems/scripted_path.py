"""`ScriptedEndEffectorPath`: a circle for the hand, then the gripper closes and opens again."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import BasicVector, LeafSystem

from trivla_drake.station.panda_driver import MAX_GRIPPER_WIDTH


@dataclass
class CirclePath:
    """A horizontal circle traced by the hand pointing down, then a gripper close/open."""

    # Centre of the circle in the world frame [m].
    center: tuple[float, float, float] = (0.45, 0.0, 0.3)
    # Radius [m].
    radius: float = 0.1
    # Time for one lap [s]; the hand starts at the circle's +x point.
    period: float = 4.0
    # Hand orientation as roll, pitch, yaw [rad]: (pi, 0, 0) points the fingers down.
    rpy: tuple[float, float, float] = (np.pi, 0.0, 0.0)
    # The gripper closes after this many laps, stays closed for `closed_time`, then opens [-, s].
    laps_before_grasp: float = 1.0
    closed_time: float = 1.0


class ScriptedEndEffectorPath(LeafSystem):
    """Outputs `ee_target` (RigidTransform, world frame [m]) and `gripper_width` (1-vector [m]).

    A pure function of time: it holds no state.
    """

    def __init__(self, path: CirclePath | None = None):
        super().__init__()
        self._path = path or CirclePath()
        if self._path.period <= 0:
            raise ValueError(f"CirclePath.period must be positive, got {self._path.period}")
        self._rotation = RollPitchYaw(self._path.rpy).ToRotationMatrix()
        self.DeclareAbstractOutputPort(
            "ee_target", lambda: AbstractValue.Make(RigidTransform()), self._calc_target
        )
        self.DeclareVectorOutputPort("gripper_width", 1, self._calc_gripper)

    def pose_at(self, t: float) -> RigidTransform:
        """The target pose at time t [s]."""
        p = self._path
        angle = 2 * np.pi * t / p.period
        offset = p.radius * np.array([np.cos(angle), np.sin(angle), 0.0])
        return RigidTransform(self._rotation, np.asarray(p.center) + offset)

    def _calc_target(self, context, output):
        output.set_value(self.pose_at(context.get_time()))

    def _calc_gripper(self, context, output: BasicVector):
        p = self._path
        close_at = p.laps_before_grasp * p.period
        closed = close_at <= context.get_time() < close_at + p.closed_time
        output.SetAtIndex(0, 0.0 if closed else MAX_GRIPPER_WIDTH)
