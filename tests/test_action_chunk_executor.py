"""Playing action chunks: timing after latency, holding without a chunk, temporal ensembling."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.systems.action_chunk_executor import ActionChunkExecutor, ChunkHistory, select_action

DT = 1.0 / 36.0


def test_action_k_is_played_at_its_own_time_and_late_actions_are_skipped():
    chunk = np.arange(70, dtype=float).reshape(10, 7)
    history = ChunkHistory().add(1.0, chunk, keep=1)
    np.testing.assert_array_equal(select_action(history, 1.0, DT, None), chunk[0])
    # Published 0.1 s late (latency): play action round(0.1 / dt) = 4, not action 0.
    np.testing.assert_array_equal(select_action(history, 1.1, DT, None), chunk[4])
    assert select_action(history, 1.0 + 10 * DT, DT, None) is None  # the chunk has run out


def test_temporal_ensembling_weights_older_chunks_more():
    old, new = np.zeros((10, 7)), np.ones((10, 7))
    history = ChunkHistory().add(0.0, old, keep=4).add(2 * DT, new, keep=4)
    plain = select_action(history, 3 * DT, DT, None)
    ensembled = select_action(history, 3 * DT, DT, 0.5)
    np.testing.assert_array_equal(plain, new[1])
    w_old, w_new = 1.0, np.exp(-0.5)
    np.testing.assert_allclose(ensembled, np.full(7, w_new / (w_old + w_new)))


def test_executor_holds_without_a_chunk_and_follows_one():
    from pydrake.systems.analysis import Simulator

    executor = ActionChunkExecutor()
    context = executor.CreateDefaultContext()
    q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785, 0.04, 0.04] + [0.0] * 9)
    executor.GetInputPort("robot_state").FixValue(context, q)
    executor.GetInputPort("action_chunk").FixValue(context, None)
    executor.GetInputPort("action_chunk_stamp").FixValue(context, [np.nan])
    simulator = Simulator(executor, context)
    simulator.Initialize()
    start = executor.GetOutputPort("ee_target").Eval(context).translation().copy()
    simulator.AdvanceTo(0.2)
    np.testing.assert_allclose(executor.GetOutputPort("ee_target").Eval(context).translation(), start)
    assert executor.played_actions(context) == 0

    chunk = np.zeros((10, 7))
    chunk[:, 2] = 0.005  # up 5 mm per step
    chunk[:, 6] = -1.0  # close
    executor.GetInputPort("action_chunk").FixValue(context, chunk)
    next_tick = np.ceil(context.get_time() / DT) * DT  # a chunk observed at a control tick
    executor.GetInputPort("action_chunk_stamp").FixValue(context, [next_tick])
    simulator.AdvanceTo(context.get_time() + 20 * DT)
    end = executor.GetOutputPort("ee_target").Eval(context).translation()
    assert executor.played_actions(context) == 10
    assert end[2] - start[2] == pytest.approx(0.05, abs=1e-9)  # 10 steps, then it holds
    assert executor.GetOutputPort("gripper_target").Eval(context)[0] == 0.0


def test_outputs_do_not_feed_through_from_inputs():
    """The executors' and the diff-IK's outputs read their discrete state alone: Drake must not see a direct
    feedthrough (a false algebraic loop in other wirings, and needless recomputation)."""
    from trivla_drake.systems.action_executor import ActionExecutor
    from trivla_drake.systems.diffik_system import DifferentialIKSystem

    for system in (ActionChunkExecutor(), ActionExecutor(), DifferentialIKSystem()):
        for i in range(system.num_input_ports()):
            for o in range(system.num_output_ports()):
                assert not system.HasDirectFeedthrough(i, o), (type(system).__name__, i, o)


@pytest.mark.parametrize("keep", [0, -1, 2.5, True])
def test_keep_chunks_must_be_a_positive_integer(keep):
    with pytest.raises(ValueError, match="keep_chunks"):
        ActionChunkExecutor(ensemble_decay=0.1, keep_chunks=keep)
