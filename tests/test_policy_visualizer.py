"""The Meshcat drawing of the hand target and the predicted chunk."""

from __future__ import annotations

import struct

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from trivla_drake.station.meshcat_setup import make_meshcat
from trivla_drake.systems.policy_visualizer import PolicyMeshcatVisualizer, chunk_path


def _translation_sent(meshcat, path: str) -> np.ndarray:
    """The translation of the last transform Meshcat holds for `path` (its msgpack message: a 16-float array,
    column-major 4x4, each float 0xcb + 8 big-endian bytes)."""
    packed = meshcat._GetPackedTransform(path)
    start = packed.index(b"\xdc\x00\x10") + 3
    values = [struct.unpack(">d", packed[start + 9 * i + 1:start + 9 * i + 9])[0] for i in range(16)]
    return np.array(values).reshape(4, 4, order="F")[:3, 3]


def test_draws_target_triad_and_chunk_path():
    meshcat = make_meshcat()
    visualizer = PolicyMeshcatVisualizer(meshcat)
    context = visualizer.CreateDefaultContext()
    visualizer.GetInputPort("ee_target").FixValue(context, RigidTransform([0.4, 0.0, 0.3]))
    chunk = np.zeros((10, 7))
    chunk[:, 0] = 0.01  # 1 cm forward per step
    visualizer.GetInputPort("action_chunk").FixValue(context, chunk)
    for path in ("trivla/ee_target/x", "trivla/chunk/0", "trivla/chunk/9"):
        assert meshcat.HasPath(path), path  # made when the system is built
    Simulator(visualizer, context).Initialize()  # its periodic publish at t = 0 draws the inputs
    np.testing.assert_allclose(_translation_sent(meshcat, "trivla/ee_target"), [0.4, 0.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(_translation_sent(meshcat, "trivla/chunk/0"), [0.41, 0.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(_translation_sent(meshcat, "trivla/chunk/9"), [0.5, 0.0, 0.3], atol=1e-12)


def test_chunk_path_integrates_clipped_translations():
    chunk = np.zeros((10, 7))
    chunk[:, 0] = 0.01
    chunk[:, 2] = -0.5  # beyond the 1 cm bound: clipped like the executor does
    path = chunk_path(np.array([0.4, 0.0, 0.3]), chunk)
    np.testing.assert_allclose(path[-1], [0.5, 0.0, 0.2], atol=1e-12)
    np.testing.assert_allclose(np.diff(path[:, 0]), 0.01)


def test_chunk_path_turns_base_frame_translations_into_the_world():
    """With the base turned 90 degrees about z, a chunk moving along the base's x moves along the world's y."""
    chunk = np.zeros((10, 7))
    chunk[:, 0] = 0.01
    R_WB = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    path = chunk_path(np.array([0.4, 0.0, 0.3]), chunk, R_WB=R_WB)
    np.testing.assert_allclose(path[-1], [0.4, 0.1, 0.3], atol=1e-12)
