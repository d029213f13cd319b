"""The station's physics: grasp and lift a block, press the button, NaN targets hold the arm."""

from __future__ import annotations

import logging

import numpy as np


def test_panda_grasps_and_lifts_a_block(closed_loop):
    start = closed_loop.body_position("block_red", "block").copy()
    closed_loop.go([start[0], start[1], 0.15], 0.08, 1.5)
    closed_loop.go([start[0], start[1], 0.025], 0.08, 1.5)
    closed_loop.go([start[0], start[1], 0.025], 0.0, 0.8)
    closed_loop.go([start[0], start[1], 0.20], 0.0, 1.5)
    lifted = closed_loop.body_position("block_red", "block")
    assert lifted[2] > start[2] + 0.15, lifted
    np.testing.assert_allclose(lifted[:2], start[:2], atol=0.01)
    # Opening the hand drops it back onto the table.
    closed_loop.go([start[0], start[1], 0.20], 0.08, 1.5)
    assert closed_loop.body_position("block_red", "block")[2] < 0.03


def test_tracks_a_reachable_target_without_steady_state_error(closed_loop):
    target = np.array([0.5, -0.1, 0.25])
    closed_loop.go(target, 0.08, 3.0)
    # Gravity-compensated PD tracking of the integrated setpoint: millimetre accuracy.
    np.testing.assert_allclose(closed_loop.tcp_position(), target, atol=2e-3)


def test_pressing_the_button_toggles_the_lamp(closed_loop):
    assert closed_loop.output("lamp.on")[0] == 0.0
    cap = closed_loop.body_position("button", "cap")
    closed_loop.go([cap[0], cap[1], 0.12], 0.0, 1.5)
    closed_loop.go([cap[0], cap[1], 0.035], 0.0, 1.0)
    closed_loop.go([cap[0], cap[1], 0.12], 0.0, 1.0)
    assert closed_loop.output("lamp.on")[0] == 1.0
    lamp = closed_loop.plant.GetJointByName("lamp_lift")
    assert lamp.get_translation(closed_loop.plant_context) > 0.01  # raised into view
    # A second press turns it off again.
    closed_loop.go([cap[0], cap[1], 0.035], 0.0, 1.0)
    closed_loop.go([cap[0], cap[1], 0.12], 0.0, 1.0)
    assert closed_loop.output("lamp.on")[0] == 0.0


def test_nan_target_is_rejected_and_the_arm_holds(closed_loop, caplog):
    closed_loop.go([0.45, 0.0, 0.3], 0.08, 1.5)
    q_before = closed_loop.output("panda.state")[:7].copy()
    with caplog.at_level(logging.ERROR):
        closed_loop.go([np.nan, 0.0, 0.3], 0.08, 0.5)
    assert "ee_target" in caplog.text and "NaN" in caplog.text
    # Said once when it starts, not on every one of the half second's 50 ticks.
    assert sum("rejected" in r.getMessage() for r in caplog.records) == 1
    status = closed_loop.diffik.GetOutputPort("status").Eval(closed_loop.diffik.GetMyContextFromRoot(closed_loop.context))
    assert status[0] == 3.0
    q_after = closed_loop.output("panda.state")[:7]
    assert np.all(np.isfinite(q_after))
    np.testing.assert_allclose(q_after, q_before, atol=2e-3)
