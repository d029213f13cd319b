"""System 1's tool-centre-point features: exact Panda kinematics in torch, wired into the state input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from trivla_drake.nn import TriVLA, make_config
from trivla_drake.nn.panda_tcp import PandaTcpFeatures
from trivla_drake.robot.panda_kinematics import PandaKinematics


def test_tcp_pose_matches_pinocchio():
    kinematics, features = PandaKinematics(), PandaTcpFeatures()
    q = np.random.default_rng(0).uniform(kinematics.q_lower, kinematics.q_upper, size=(8, 7))
    poses = features.pose(torch.tensor(q, dtype=torch.float32)).double().numpy()
    for qi, pose in zip(q, poses):
        np.testing.assert_allclose(pose, np.asarray(kinematics.ee_pose(qi)), atol=2e-6)


def test_features_are_position_and_two_rotation_columns():
    features = PandaTcpFeatures()
    state = torch.tensor([[0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785] + [0.04] * 2 + [0.0] * 9])
    pose, out = features.pose(state)[0], features(state)[0]
    np.testing.assert_allclose(out[:3], (pose[:3, 3] - torch.tensor([0.5, 0.0, 0.2])) / 0.2, atol=1e-6)
    np.testing.assert_allclose(out[3:6], pose[:3, 0], atol=1e-6)
    np.testing.assert_allclose(out[6:], pose[:3, 1], atol=1e-6)
    with pytest.raises(ValueError, match="joint angles"):
        features(torch.zeros(2, 5))


def test_tcp_features_need_panda_joint_names():
    config = make_config("tiny")
    names = ("wrist",) + tuple(config.state_names[1:])
    with pytest.raises(ValueError, match="tcp_features"):
        dataclasses.replace(config, state_names=names)
    dataclasses.replace(config, state_names=names, policy=dataclasses.replace(config.policy, tcp_features=False))


def test_state_token_sees_the_tcp_only_when_configured():
    with_tcp = TriVLA(make_config("tiny"), load_pretrained=False)
    config = make_config("tiny")
    without = TriVLA(dataclasses.replace(config, policy=dataclasses.replace(config.policy, tcp_features=False)),
                     load_pretrained=False)
    assert with_tcp.policy.state_input_dim == without.policy.state_input_dim + 9
    state = torch.zeros(2, 18)
    state[1, 0] = 0.5  # turning joint 1 moves the tcp
    inputs = with_tcp._state_input(state)
    torch.testing.assert_close(inputs[:, :18], without._state_input(state))
    torch.testing.assert_close(inputs[:, 18:], PandaTcpFeatures()(state))
    assert not torch.allclose(inputs[0, 18:], inputs[1, 18:])
    q_s = with_tcp.encode_state_batch(state, torch.zeros(2, dtype=torch.long))
    assert q_s.shape == (2, with_tcp.config.policy.hidden_size)
