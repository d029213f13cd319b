"""PandaKinematics: the reduced 7-joint model, its forward kinematics and its Jacobian."""

import numpy as np
import pinocchio as pin
import pytest

from trivla_drake.robot.osqp_diffik import PANDA_HOME, pose_error
from trivla_drake.robot.panda_description import ARM_JOINTS, original_panda_urdf
from trivla_drake.robot.panda_kinematics import PandaKinematics

# Franka's published modified-DH table (a [m], d [m], alpha [rad]) for joints 1-7 and the flange.
_DH = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -np.pi / 2),
    (0.0, 0.316, np.pi / 2),
    (0.0825, 0.0, np.pi / 2),
    (-0.0825, 0.384, -np.pi / 2),
    (0.0, 0.0, np.pi / 2),
    (0.088, 0.0, np.pi / 2),
    (0.0, 0.107, 0.0),
]


def _rot_x(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _translation(x, y, z):
    pose = np.eye(4)
    pose[:3, 3] = x, y, z
    return pose


def _dh_tcp_pose(q):
    """The tool-centre point from the DH table, written independently of the URDF."""
    pose = np.eye(4)
    for (a, d, alpha), theta in zip(_DH, list(q) + [0.0]):
        pose = pose @ _rot_x(alpha) @ _translation(a, 0, 0) @ _rot_z(theta) @ _translation(0, 0, d)
    # The hand is turned by -45 degrees about the flange axis; the TCP is 0.1034 m out from it.
    return pose @ _rot_z(-np.pi / 4) @ _translation(0, 0, 0.1034)


@pytest.fixture(scope="module")
def kinematics():
    return PandaKinematics()


def _random_configurations(kinematics, count, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(kinematics.q_lower, kinematics.q_upper, size=(count, kinematics.nq))


def test_reduced_model_has_the_seven_arm_joints_and_their_urdf_limits(kinematics):
    assert kinematics.nq == 7
    assert kinematics.joint_names == ARM_JOINTS
    np.testing.assert_allclose(
        kinematics.q_lower, [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
    )
    np.testing.assert_allclose(kinematics.q_upper, [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
    np.testing.assert_allclose(kinematics.v_max, [2.175] * 4 + [2.61] * 3)


def test_forward_kinematics_matches_the_dh_table(kinematics):
    for q in _random_configurations(kinematics, 50, seed=0):
        np.testing.assert_allclose(kinematics.ee_pose(q), _dh_tcp_pose(q), atol=1e-12)


def test_home_pose_points_the_hand_down(kinematics):
    pose = kinematics.ee_pose(np.array(PANDA_HOME))
    np.testing.assert_allclose(pose[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-3)
    np.testing.assert_allclose(pose[:3, 3], [0.307, 0.0, 0.487], atol=1e-3)


def test_locked_fingers_do_not_move_the_tcp(kinematics):
    full = pin.buildModelFromUrdf(str(original_panda_urdf()))
    data = full.createData()
    frame = full.getFrameId("panda_hand_tcp")
    for q in _random_configurations(kinematics, 10, seed=1):
        pin.framesForwardKinematics(full, data, np.concatenate([q, [0.04, 0.04]]))
        np.testing.assert_allclose(kinematics.ee_pose(q), data.oMf[frame].homogeneous, atol=1e-14)


def test_jacobian_matches_central_finite_differences(kinematics):
    step = 1e-6
    for q in _random_configurations(kinematics, 30, seed=2):
        jacobian = kinematics.ee_jacobian(q)
        for joint in range(kinematics.nq):
            dq = np.zeros(kinematics.nq)
            dq[joint] = step
            # pose_error is the world-frame twist [v; w] from one pose to the other in unit time.
            column = pose_error(kinematics.ee_pose(q - dq), kinematics.ee_pose(q + dq)) / (2 * step)
            np.testing.assert_allclose(jacobian[:, joint], column, atol=1e-7)


def test_poses_are_never_stale_after_jacobian_calls(kinematics):
    q_a, q_b = _random_configurations(kinematics, 2, seed=3)
    expected_b = _dh_tcp_pose(q_b)
    kinematics.ee_jacobian(q_a)
    np.testing.assert_allclose(kinematics.ee_pose(q_b), expected_b, atol=1e-12)
    pose, jacobian = kinematics.forward(q_a)
    np.testing.assert_allclose(pose, _dh_tcp_pose(q_a), atol=1e-12)
    np.testing.assert_allclose(jacobian, kinematics.ee_jacobian(q_a), atol=0)


def test_returned_arrays_are_owned_by_the_caller(kinematics):
    q_a, q_b = _random_configurations(kinematics, 2, seed=4)
    pose, jacobian = kinematics.forward(q_a)
    saved = pose.copy(), jacobian.copy()
    kinematics.forward(q_b)
    np.testing.assert_array_equal(pose, saved[0])
    np.testing.assert_array_equal(jacobian, saved[1])


def test_other_end_effector_frame(kinematics):
    flange = PandaKinematics(ee_frame="panda_link8")
    q = np.array(PANDA_HOME)
    offset = np.linalg.inv(flange.ee_pose(q)) @ kinematics.ee_pose(q)
    np.testing.assert_allclose(offset[:3, 3], [0, 0, 0.1034], atol=1e-12)


@pytest.mark.parametrize(
    "q, match",
    [
        (np.full(7, np.nan), "q contains NaN/inf"),
        (np.array([0, 0, 0, -1, 0, np.inf, 0.0]), "q contains NaN/inf"),
        (np.zeros(9), r"q must have shape \(7,\)"),
    ],
)
def test_bad_configuration_raises_naming_q(kinematics, q, match):
    with pytest.raises(ValueError, match=match):
        kinematics.ee_pose(q)


def test_unknown_names_raise():
    with pytest.raises(ValueError, match="ee_frame"):
        PandaKinematics(ee_frame="no_such_frame")
    with pytest.raises(ValueError, match="arm_joints"):
        PandaKinematics(arm_joints=("panda_joint1", "no_such_joint"))
