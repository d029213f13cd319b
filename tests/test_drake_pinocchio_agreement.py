"""Drake (converted URDF) and pinocchio (original URDF) agree on the hand's pose and Jacobian."""

from __future__ import annotations

import numpy as np
import pytest
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable

from trivla_drake.robot.panda_assets import drake_panda_urdf
from trivla_drake.robot.panda_description import EE_FRAME
from trivla_drake.robot.panda_kinematics import PandaKinematics


@pytest.fixture(scope="module")
def drake_panda():
    plant = MultibodyPlant(0.0)
    (instance,) = Parser(plant).AddModels(str(drake_panda_urdf()))
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("panda_link0", instance))
    plant.Finalize()
    return plant, plant.CreateDefaultContext()


def test_hand_pose_and_jacobian_agree_for_random_configurations(drake_panda):
    plant, context = drake_panda
    kinematics = PandaKinematics()
    frame = plant.GetFrameByName(EE_FRAME)
    rng = np.random.default_rng(7)
    for _ in range(50):
        q = rng.uniform(kinematics.q_lower, kinematics.q_upper)
        plant.SetPositions(context, np.concatenate([q, [0.02, 0.02]]))
        X_drake = frame.CalcPoseInWorld(context).GetAsMatrix4()
        np.testing.assert_allclose(kinematics.ee_pose(q), X_drake, atol=1e-9)
        J_drake = plant.CalcJacobianSpatialVelocity(
            context, JacobianWrtVariable.kV, frame, np.zeros(3), plant.world_frame(), plant.world_frame()
        )[:, :7]
        # pinocchio's rows are [v; w], Drake's [w; v].
        J_pin = kinematics.ee_jacobian(q)
        np.testing.assert_allclose(J_pin[:3], J_drake[3:], atol=1e-9)
        np.testing.assert_allclose(J_pin[3:], J_drake[:3], atol=1e-9)
