"""The robot base's pose in the world, X_WB: given as an argument, or read from the weld in a plant.

The policy's actions, the diff-IK's kinematics and System 1's tool-centre point are all in the Panda's
base frame B (`panda_link0`); the systems' `ee_target` ports are in the world W. X_WB links the two.
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant

BASE_FRAME = "panda_link0"


def base_pose_matrix(X_WB: RigidTransform | None, name: str = "X_WB") -> np.ndarray | None:
    """X_WB as a 4x4 matrix, or None when it is None or exactly the identity (the caller may then skip the
    transform, or apply an exact identity). TypeError naming `name` unless it is a RigidTransform; ValueError
    if it holds NaN/inf."""
    if X_WB is None:
        return None
    if not isinstance(X_WB, RigidTransform):
        raise TypeError(f"{name} must be a pydrake.math.RigidTransform (the pose of the robot's base in the world), "
                        f"got {type(X_WB).__name__}")
    matrix = X_WB.GetAsMatrix4()
    if not np.isfinite(matrix).all():
        raise ValueError(f"{name} contains NaN/inf: {matrix.tolist()}")
    return None if np.array_equal(matrix, np.eye(4)) else matrix


def robot_base_pose(plant: MultibodyPlant, model_instance, frame_name: str = BASE_FRAME) -> RigidTransform:
    """X_WB: the pose in the world of `frame_name` (the Panda's `panda_link0`) of `model_instance`, read from a
    finalized `plant`. ValueError unless that frame exists and its body is welded to the world (a base that
    moves would change X_WB during the run; the policy takes it as fixed)."""
    if not plant.is_finalized():
        raise ValueError("robot_base_pose: call plant.Finalize() first (the base's weld is read from the plant)")
    instance_name = plant.GetModelInstanceName(model_instance)
    if not plant.HasFrameNamed(frame_name, model_instance):
        raise ValueError(f"robot_base_pose: model instance '{instance_name}' has no frame '{frame_name}'")
    frame = plant.GetFrameByName(frame_name, model_instance)
    welded = [body.index() for body in plant.GetBodiesWeldedTo(plant.world_body())]
    if frame.body().index() not in welded:
        raise ValueError(f"robot_base_pose: {instance_name}::{frame_name} is not welded to the world (weld it, e.g. "
                         f"plant.WeldFrames(plant.world_frame(), plant.GetFrameByName('{frame_name}'), X_WB))")
    return plant.CalcRelativeTransform(plant.CreateDefaultContext(), plant.world_frame(), frame)
