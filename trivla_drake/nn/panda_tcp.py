"""The Panda's tool-centre-point pose from its joint angles, in torch (System 1's state features).

The policy's actions move the tool-centre point in the world, but its state input is joint angles:
without help it has to learn the arm's forward kinematics from a few hundred demonstrations on top
of everything else. `PandaTcpFeatures` computes the pose exactly (the Franka Panda URDF's chain, the
same one `trivla_drake.robot.PandaKinematics` reads with pinocchio; a test checks they agree), as
CALVIN's robot observation, which the paper's policy reads, carries the end-effector pose too.

Frame: the arm's base link (`panda_link0`, at the world origin in our scenes); the tool-centre point
is `panda_hand_tcp`, 0.2104 m along joint 7's axis and turned -45 degrees about it.
"""

from __future__ import annotations

import math

import torch
from torch import nn

# Each revolute joint's origin in its parent's frame: (xyz [m], roll about x [rad]); all rotate about z.
_JOINT_ORIGINS = (
    ((0.0, 0.0, 0.333), 0.0),
    ((0.0, 0.0, 0.0), -math.pi / 2),
    ((0.0, -0.316, 0.0), math.pi / 2),
    ((0.0825, 0.0, 0.0), math.pi / 2),
    ((-0.0825, 0.384, 0.0), -math.pi / 2),
    ((0.0, 0.0, 0.0), math.pi / 2),
    ((0.088, 0.0, 0.0), math.pi / 2),
)
_TCP_IN_JOINT7 = ((0.0, 0.0, 0.2104), -math.pi / 4)  # xyz [m], yaw about z [rad]
# Features: (position - centre) / scale, then the rotation matrix's first two columns (6D rotation).
_CENTRE = (0.5, 0.0, 0.2)
_SCALE = 0.2
FEATURE_DIM = 9


def _transform(xyz, rotation: torch.Tensor) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = rotation
    T[:3, 3] = torch.tensor(xyz, dtype=torch.float64)
    return T


def _rot_x(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)


def _rot_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


_CENTRE_TENSOR = torch.tensor(_CENTRE)  # made once: `normalize_position` runs on every System 1 tick


def normalize_position(position: torch.Tensor) -> torch.Tensor:
    """Positions (..., 3) [m] in the base frame -> the features' position units: (p - centre) / scale."""
    return (position - _CENTRE_TENSOR.to(device=position.device, dtype=position.dtype)) / _SCALE


def denormalize_position(features: torch.Tensor) -> torch.Tensor:
    """The inverse of `normalize_position`: feature units (..., 3) -> positions [m]."""
    return features * _SCALE + _CENTRE_TENSOR.to(device=features.device, dtype=features.dtype)


class PandaTcpFeatures(nn.Module):
    """Joint angles (B, >= 7) [rad], the first 7 entries used -> features (B, 9): the tcp position,
    centred on (0.5, 0, 0.2) m and divided by 0.2 m, and the first two columns of its rotation."""

    def __init__(self) -> None:
        super().__init__()
        origins = torch.stack([_transform(xyz, _rot_x(roll)) for xyz, roll in _JOINT_ORIGINS])
        self.register_buffer("joint_origins", origins.float(), persistent=False)  # (7, 4, 4)
        tcp = _transform(_TCP_IN_JOINT7[0], _rot_z(_TCP_IN_JOINT7[1]))
        self.register_buffer("tcp_in_joint7", tcp.float(), persistent=False)

    def pose(self, joints: torch.Tensor) -> torch.Tensor:
        """(B, >= 7) joint angles -> (B, 4, 4) tcp pose in the base frame."""
        if joints.dim() != 2 or joints.shape[-1] < 7:
            raise ValueError(f"joint angles must be (B, >=7), got {tuple(joints.shape)}")
        q = joints[:, :7].to(self.joint_origins.dtype)
        c, s = torch.cos(q), torch.sin(q)
        zero, one = torch.zeros_like(q), torch.ones_like(q)
        # (B, 7, 4, 4) rotations about z by each joint angle.
        rz = torch.stack(
            [
                torch.stack([c, -s, zero, zero], -1),
                torch.stack([s, c, zero, zero], -1),
                torch.stack([zero, zero, one, zero], -1),
                torch.stack([zero, zero, zero, one], -1),
            ],
            -2,
        )
        X = torch.eye(4, dtype=q.dtype, device=q.device).expand(q.shape[0], 4, 4)
        for i in range(7):
            X = X @ self.joint_origins[i] @ rz[:, i]
        return X @ self.tcp_in_joint7

    def forward(self, joints: torch.Tensor) -> torch.Tensor:
        X = self.pose(joints)
        position = normalize_position(X[:, :3, 3])
        rotation = X[:, :3, :2].transpose(1, 2).reshape(X.shape[0], 6)
        return torch.cat([position, rotation], dim=-1)
