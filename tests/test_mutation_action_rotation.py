"""The action's rotation increment turns about the world axis it names, for x and y as well as z.

The other action tests turn only about z (a hand's yaw), so swapping the x and y components of the
rotation vector in `apply_action` or `delta_action` went unnoticed. The expected orientations here come
from scipy's Rotation, independently of the code under test.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from trivla_drake.systems.action_executor import OPEN_WIDTH, apply_action, delta_action
from trivla_drake.tasks.scene import tcp_pose

START = tcp_pose([0.45, 0.05, 0.25], 0.3)  # the hand pointing down, turned 0.3 rad about z: not the identity

ROTATION_VECTORS = {
    "about x": [0.04, 0.0, 0.0],
    "about y": [0.0, 0.04, 0.0],
    "mixed": [0.03, -0.02, 0.01],
}


@pytest.mark.parametrize("rotvec", ROTATION_VECTORS.values(), ids=ROTATION_VECTORS.keys())
def test_rotation_increment_turns_about_the_world_axis_it_names(rotvec):
    translation = np.array([0.004, -0.003, 0.002])
    action = np.concatenate([translation, rotvec, [1.0]])
    X_next, width = apply_action(START, action)

    expected_R = Rotation.from_rotvec(rotvec).as_matrix() @ START[:3, :3]  # world axes: left multiplication
    np.testing.assert_allclose(X_next[:3, :3], expected_R, atol=1e-12)
    np.testing.assert_allclose(X_next[:3, 3], START[:3, 3] + translation, atol=1e-15)
    np.testing.assert_array_equal(X_next[3], [0.0, 0.0, 0.0, 1.0])
    assert width == OPEN_WIDTH

    # Five equal increments about one fixed world axis make one turn five times as large.
    X = START
    for _ in range(5):
        X, _ = apply_action(X, np.concatenate([[0.0, 0.0, 0.0], rotvec, [1.0]]))
    np.testing.assert_allclose(X[:3, :3], Rotation.from_rotvec(5 * np.asarray(rotvec)).as_matrix() @ START[:3, :3],
                               atol=1e-12)


@pytest.mark.parametrize("rotvec", ROTATION_VECTORS.values(), ids=ROTATION_VECTORS.keys())
def test_delta_action_is_the_inverse_of_apply_action(rotvec):
    goal = np.eye(4)
    goal[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix() @ START[:3, :3]
    goal[:3, 3] = START[:3, 3] + [-0.002, 0.005, -0.001]

    action = delta_action(START, goal, -1.0)
    np.testing.assert_allclose(action, [-0.002, 0.005, -0.001, *rotvec, -1.0], atol=1e-12)
    X_next, _ = apply_action(START, action)
    np.testing.assert_allclose(X_next, goal, atol=1e-12)
    # Going back is the opposite rotation vector.
    np.testing.assert_allclose(delta_action(goal, START, 1.0)[3:6], -np.asarray(rotvec), atol=1e-12)
