"""`PolicyMeshcatVisualizer`: draws the end-effector target and the predicted chunk in Meshcat."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import Cylinder, Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import LeafSystem

from trivla_drake.systems.action_executor import DEFAULT_ACTION_SPACE
from trivla_drake.systems.robot_base import base_pose_matrix

_AXES = (
    (RotationMatrix.MakeYRotation(np.pi / 2), [1, 0, 0], Rgba(0.9, 0.1, 0.1, 1)),
    (RotationMatrix.MakeXRotation(-np.pi / 2), [0, 1, 0], Rgba(0.1, 0.8, 0.1, 1)),
    (RotationMatrix(), [0, 0, 1], Rgba(0.1, 0.2, 0.9, 1)),
)


def chunk_path(start: np.ndarray, chunk: np.ndarray, horizon: int = 10, R_WB: np.ndarray | None = None) -> np.ndarray:
    """Points (horizon, 3) in the world [m] the chunk's translations trace from `start` (world), each step clipped
    to the action bounds as the executor clips them; the translations are in the robot's base frame, turned into
    the world by `R_WB` (the base's orientation; None: the base is unrotated)."""
    low, high = DEFAULT_ACTION_SPACE.low[:3], DEFAULT_ACTION_SPACE.high[:3]
    steps = np.cumsum(np.clip(np.asarray(chunk)[:horizon, :3], low, high), axis=0)
    return np.asarray(start) + (steps if R_WB is None else steps @ np.asarray(R_WB).T)


class PolicyMeshcatVisualizer(LeafSystem):
    """Publishes, every `period_s`, a triad at `ee_target` and one sphere per action of the chunk.

    Inputs: `ee_target` (RigidTransform of the tcp in the world [m]), `action_chunk` (abstract float
    numpy (H, 7) or None; the first `horizon` rows are drawn). The chunk is drawn as the path its
    translations trace from the current target (`X_WB`: the robot base's pose in the world, as given to the
    policy; the chunk's translations are in the base frame). Poses are also written into a Meshcat recording
    when one is running, so saved pages show them.
    """

    def __init__(self, meshcat: Meshcat, *, period_s: float = 1.0 / 30.0, prefix: str = "trivla",
                 horizon: int = 10, triad_length: float = 0.06, X_WB: RigidTransform | None = None):
        super().__init__()
        X_WB_matrix = base_pose_matrix(X_WB, "X_WB")
        self._R_WB = None if X_WB_matrix is None else X_WB_matrix[:3, :3]
        self._meshcat = meshcat
        self._prefix = prefix
        self._horizon = horizon
        self._target = self.DeclareAbstractInputPort("ee_target", AbstractValue.Make(RigidTransform()))
        self._chunk = self.DeclareAbstractInputPort("action_chunk", AbstractValue.Make(None))
        self.DeclarePeriodicPublishEvent(period_s, 0.0, self._publish)
        for rotation, axis, rgba in _AXES:
            path = f"{prefix}/ee_target/{'xyz'[int(np.argmax(axis))]}"
            meshcat.SetObject(path, Cylinder(0.004, triad_length), rgba)
            meshcat.SetTransform(path, RigidTransform(rotation, 0.5 * triad_length * np.asarray(axis, float)))
        for k in range(horizon):
            shade = 1.0 - 0.6 * k / max(1, horizon - 1)
            meshcat.SetObject(f"{prefix}/chunk/{k}", Sphere(0.006), Rgba(1.0, 0.55 * shade, 0.0, 0.9))

    def _publish(self, context):
        t = context.get_time()
        X_WT = self._target.Eval(context)
        self._meshcat.SetTransform(f"{self._prefix}/ee_target", X_WT, time_in_recording=t)
        chunk = self._chunk.Eval(context) if self._chunk.HasValue(context) else None
        if chunk is None:
            return
        for k, point in enumerate(chunk_path(X_WT.translation(), chunk, self._horizon, self._R_WB)):
            self._meshcat.SetTransform(f"{self._prefix}/chunk/{k}", RigidTransform(point), time_in_recording=t)
