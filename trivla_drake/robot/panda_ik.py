"""Inverse kinematics of the Panda's tool-centre point by damped least squares (no simulator).

Used to put the arm at a pose without simulating the way there: the rendered grounding scenes place the
hand along the oracle's approach (train/grounding_scenes.py). Each step solves J dq = e for the pose
error e (position [m], then rotation [rad] as the world-frame rotation vector) with damping, and clips
to the joint limits.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from trivla_drake.robot.panda_kinematics import PandaKinematics


def pose_error(current: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(6,): target minus current position [m], then the rotation taking current's orientation to
    target's as a rotation vector in world axes [rad]; both 4x4 poses."""
    rotation = current[:3, :3]
    return np.concatenate([target[:3, 3] - current[:3, 3], rotation @ pin.log3(rotation.T @ target[:3, :3])])


def solve_ik(
    kinematics: PandaKinematics,
    target: np.ndarray,
    q_start: np.ndarray,
    *,
    iterations: int = 200,
    damping: float = 1e-2,
    position_tolerance: float = 5e-4,
    rotation_tolerance: float = 5e-3,
) -> tuple[np.ndarray, float, float]:
    """Joint angles (7,) [rad] that put the tool-centre point at `target` (4x4 in the arm's base frame),
    starting from `q_start`, within the joint limits. Returns (q, position error [m], rotation error
    [rad]) of the last iterate: the caller decides whether an unreached target is acceptable."""
    target = np.asarray(target, dtype=float)
    if target.shape != (4, 4) or not np.isfinite(target).all():
        raise ValueError(f"target must be a finite 4x4 pose; got shape {target.shape}")
    if iterations < 1 or damping <= 0:
        raise ValueError(f"iterations must be >= 1 and damping > 0; got {iterations} and {damping}")
    q = np.clip(kinematics.check_configuration(q_start).copy(), kinematics.q_lower, kinematics.q_upper)
    regularizer = damping**2 * np.eye(6)
    for _ in range(iterations):
        pose, jacobian = kinematics.forward(q)
        error = pose_error(pose, target)
        if np.linalg.norm(error[:3]) < position_tolerance and np.linalg.norm(error[3:]) < rotation_tolerance:
            break
        step = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + regularizer, error)
        q = np.clip(q + step, kinematics.q_lower, kinematics.q_upper)
    error = pose_error(kinematics.ee_pose(q), target)
    return q, float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:]))
