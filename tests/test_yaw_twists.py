"""Yaw twists (`collect --yaw-twists`): once per episode, on the open hand's way down to its first
grasp, its yaw is turned off the expert's; the expert turning first holds its position until it has
turned back, then grasps. Collect records the disturbed frames, so their later chunk entries are no
labels. Bad settings are refused naming the field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trivla_drake.data.lerobot import PERTURBED_FRAMES_KEY, YAW_TWISTS_KEY, LeRobotReader
from trivla_drake.data.samples import TrainingSamples
from trivla_drake.eval.action_noise import YawTwists
from trivla_drake.tasks.motions import Waypoint
from trivla_drake.tasks.oracle import TURN_FIRST_RAD, OraclePolicy
from trivla_drake.tasks.scene import tcp_pose


def _at(z: float) -> dict:
    return {"ee_target": tcp_pose([0.5, 0.0, z], 0.0)}


def test_the_twist_waits_for_the_open_hand_to_come_down_then_turns_about_the_vertical_once():
    twist = YawTwists(start_z=(0.1, 0.1), angle=(0.5, 0.5), rate=0.04).start(np.random.default_rng(0))
    down = np.array([0.001, 0.0, -0.004, 0.01, 0.0, 0.02, 1.0])
    level = down * [1, 1, 0, 1, 1, 1, 1]
    assert twist.apply(down, _at(0.15)) == (down, False)  # above the start height
    assert twist.apply(level, _at(0.09))[1] is False  # below it, but not coming down
    out = [twist.apply(down, _at(0.09)) for _ in range(20)]
    flags = [flag for _, flag in out]
    steps = math.ceil(0.5 / 0.04)
    assert flags == [True] * steps + [False] * (20 - steps)  # one twist per episode
    applied = np.stack([a for a, _ in out[:steps]])
    np.testing.assert_allclose(applied[:, :3], np.tile(down[:3], (steps, 1)))  # the expert's translation
    np.testing.assert_allclose(applied[:, 3:5], 0.0)
    assert abs(applied[:, 5].sum()) == pytest.approx(0.5)  # the drawn angle, about the vertical
    assert (applied[:, 6] == 1.0).all() and down[5] == 0.02  # gripper and the expert's action untouched


def test_no_twist_after_the_gripper_first_closes():
    twist = YawTwists(start_z=(0.1, 0.1)).start(np.random.default_rng(1))
    close = np.array([0.0, 0.0, -0.004, 0.0, 0.0, 0.0, -1.0])
    assert twist.apply(close, _at(0.05))[1] is False
    opened = close * [1, 1, 1, 1, 1, 1, -1]
    assert not any(twist.apply(opened, _at(0.05))[1] for _ in range(50))


def test_the_twist_needs_the_commanded_pose():
    twist = YawTwists().start(np.random.default_rng(2))
    with pytest.raises(ValueError, match="ee_target"):
        twist.apply(np.array([0.0, 0.0, -0.004, 0.0, 0.0, 0.0, 1.0]), {})


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"start_z": (0.2, 0.1)}, "start_z"), ({"angle": (0.3, 1.0)}, "angle"), ({"rate": 0.2}, "rate")],
)
def test_bad_twist_settings_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        YawTwists(**kwargs)


def test_an_expert_that_turns_first_holds_its_position_while_turned_off():
    target = Waypoint(tcp_pose([0.5, 0.0, 0.03], 0.0), 1.0, turn_first=True)
    turned = tcp_pose([0.5, 0.0, 0.10], 3 * TURN_FIRST_RAD)
    action, _ = OraclePolicy(turn_first=True)._toward(turned, target)
    np.testing.assert_allclose(action[:3], 0.0)
    assert action[5] < 0.0  # turns back
    plain, _ = OraclePolicy()._toward(turned, target)  # the expert the shipped data came from
    assert plain[2] < 0.0
    nearly, _ = OraclePolicy(turn_first=True)._toward(tcp_pose([0.5, 0.0, 0.10], 0.5 * TURN_FIRST_RAD), target)
    assert nearly[2] < 0.0


def test_twisted_collection_still_grasps_and_marks_the_twist(tmp_path):
    from trivla_drake.data.subgoals import quaternion_yaw
    from trivla_drake.eval.collect import CollectConfig, collect

    out = tmp_path / "twists"
    summary = collect(
        CollectConfig(out=str(out), episodes_per_task=1, tasks=["lift_block"], image_size=32, yaw_twists=True),
        progress=False,
    )
    assert summary["per_task"] == {"lift_block": 1}
    episode = LeRobotReader(out).episodes[0]
    assert episode[YAW_TWISTS_KEY] is True
    twisted = episode[PERTURBED_FRAMES_KEY]
    assert len(twisted) >= math.ceil(YawTwists().angle[0] / YawTwists().rate)
    samples = TrainingSamples(out, cameras=[])
    assert samples[twisted[0]]["action_is_stale"].any()
    # The hand was turned off during the twist and is back at the grasp's yaw when it closes.
    frames = LeRobotReader(out).episode_frames(0)
    yaw = np.degrees([quaternion_yaw(q) for q in np.asarray(frames["observation.tcp_pose"])[:, 3:7]])
    close = int(np.flatnonzero(np.asarray(frames["action"])[:, 6] <= 0.0)[0])
    assert close > twisted[-1]
    before = yaw[twisted[0]]
    assert np.abs(yaw[twisted[0]:close] - before).max() > 10.0
    assert abs(yaw[close] - before) < 3.0


def test_yaw_twists_and_action_noise_cannot_be_combined():
    from trivla_drake.eval.collect import CollectConfig

    with pytest.raises(ValueError, match="--yaw-twists"):
        CollectConfig(out="unused", episodes_per_task=1, yaw_twists=True, action_noise=1.0).validate()
