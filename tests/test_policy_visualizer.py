"""The Meshcat drawing of the hand target and the predicted chunk."""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform

from trivla_drake.station.meshcat_setup import make_meshcat
from trivla_drake.systems.policy_visualizer import PolicyMeshcatVisualizer, chunk_path


def test_draws_target_triad_and_chunk_path():
    meshcat = make_meshcat()
    visualizer = PolicyMeshcatVisualizer(meshcat)
    context = visualizer.CreateDefaultContext()
    visualizer.GetInputPort("ee_target").FixValue(context, RigidTransform([0.4, 0.0, 0.3]))
    chunk = np.zeros((10, 7))
    chunk[:, 0] = 0.01  # 1 cm forward per step
    visualizer.GetInputPort("action_chunk").FixValue(context, chunk)
    visualizer.ForcedPublish(context)
    for path in ("trivla/ee_target/x", "trivla/chunk/0", "trivla/chunk/9"):
        assert meshcat.HasPath(path), path


def test_chunk_path_integrates_clipped_translations():
    chunk = np.zeros((10, 7))
    chunk[:, 0] = 0.01
    chunk[:, 2] = -0.5  # beyond the 1 cm bound: clipped like the executor does
    path = chunk_path(np.array([0.4, 0.0, 0.3]), chunk)
    np.testing.assert_allclose(path[-1], [0.5, 0.0, 0.2], atol=1e-12)
    np.testing.assert_allclose(np.diff(path[:, 0]), 0.01)
