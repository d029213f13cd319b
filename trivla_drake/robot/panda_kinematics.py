"""Forward kinematics and end-effector Jacobian of the Panda arm (pinocchio, no Drake)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin

from trivla_drake.robot.panda_description import ARM_JOINTS, EE_FRAME, original_panda_urdf


class PandaKinematics:
    """The 7-joint Panda arm, fingers locked at their reference position.

    The world frame is the arm's base link (`panda_link0`). Joint limits come from the URDF.
    One `pin.Data` is reused by every call, so an instance is not thread-safe.
    """

    def __init__(
        self,
        urdf_path: str | Path | None = None,
        *,
        ee_frame: str = EE_FRAME,
        arm_joints: tuple[str, ...] = ARM_JOINTS,
    ) -> None:
        full = pin.buildModelFromUrdf(str(urdf_path or original_panda_urdf()))
        missing = [name for name in arm_joints if not full.existJointName(name)]
        if missing:
            raise ValueError(
                f"arm_joints {missing} are not in the URDF, whose joints are {list(full.names)[1:]}"
            )
        # Every joint that is not an arm joint (the fingers) is locked at the neutral configuration;
        # the fingers do not move the hand's tool-centre point, so the locked value does not matter.
        locked = [full.getJointId(name) for name in full.names[1:] if name not in arm_joints]
        self.model = pin.buildReducedModel(full, locked, pin.neutral(full))
        if not self.model.existFrame(ee_frame):
            raise ValueError(f"ee_frame {ee_frame!r} is not a frame of the URDF")
        self.data = self.model.createData()
        self.ee_frame = ee_frame
        self._ee_id = self.model.getFrameId(ee_frame)
        self.joint_names = tuple(self.model.names[1:])
        # Copies, so that a caller editing them cannot change the model's limits.
        self.q_lower = self.model.lowerPositionLimit.copy()  # [rad]
        self.q_upper = self.model.upperPositionLimit.copy()  # [rad]
        self.v_max = self.model.velocityLimit.copy()  # [rad/s]

    @property
    def nq(self) -> int:
        """Number of arm joints (7)."""
        return self.model.nq

    def check_configuration(self, q: np.ndarray) -> np.ndarray:
        """`q` as a float array of shape (nq,); ValueError naming `q` if it has another shape or NaN/inf."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.nq,):
            raise ValueError(f"q must have shape ({self.nq},), got {q.shape}")
        if not np.isfinite(q).all():
            raise ValueError(f"q contains NaN/inf: {q}")
        return q

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """End-effector pose (4x4) and 6xnq Jacobian from one kinematics pass; see the methods below."""
        q = self.check_configuration(q)
        # computeJointJacobians runs the forward kinematics (data.oMi) the Jacobian needs; the frame
        # placement is then refreshed explicitly, since no Jacobian routine updates data.oMf.
        pin.computeJointJacobians(self.model, self.data, q)
        pose = pin.updateFramePlacement(self.model, self.data, self._ee_id).homogeneous
        jacobian = pin.getFrameJacobian(self.model, self.data, self._ee_id, pin.LOCAL_WORLD_ALIGNED)
        return pose, jacobian

    def pose(self, q: np.ndarray) -> np.ndarray:
        """`ee_pose(q)` by forward kinematics alone (no Jacobian): for callers that need the pose only."""
        q = self.check_configuration(q)
        pin.forwardKinematics(self.model, self.data, q)
        return pin.updateFramePlacement(self.model, self.data, self._ee_id).homogeneous

    def ee_pose(self, q: np.ndarray) -> np.ndarray:
        """Pose of the end-effector frame in the world (base) frame, as a 4x4 homogeneous matrix."""
        return self.forward(q)[0]

    def ee_jacobian(self, q: np.ndarray) -> np.ndarray:
        """6xnq Jacobian of the end-effector frame, expressed in LOCAL_WORLD_ALIGNED.

        Rows are pinocchio's order [v; w]: rows 0-2 map joint velocities to the linear velocity of
        the frame origin, rows 3-5 to the angular velocity, both in world axes. Drake's spatial
        velocities are ordered [w; v], so swap the row blocks when comparing with Drake.
        """
        return self.forward(q)[1]
