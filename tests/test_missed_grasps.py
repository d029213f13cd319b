"""Missed grasps (`collect --missed-grasps`): once per episode, on the open hand's way down to its first
grasp, the applied actions take the hand beside where the expert was heading and close it there; the
expert with `regrasp` sees its hand closed against its plan, opens, rises and grasps again. Collect
records the disturbed frames, so their later chunk entries are no labels. Bad settings are refused
naming the field."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.data.lerobot import MISSED_GRASPS_KEY, PERTURBED_FRAMES_KEY, LeRobotReader
from trivla_drake.data.samples import TrainingSamples
from trivla_drake.eval.missed_grasps import MissedGrasps
from trivla_drake.systems.action_executor import apply_action
from trivla_drake.tasks.scene import tcp_pose

DOWN = np.array([0.0, 0.0, -0.003, 0.0, 0.0, 0.0, 1.0])


def _play(state, X: np.ndarray, action: np.ndarray, steps: int):
    """Offers `action` `steps` times from the commanded pose X, applying what comes out; returns the
    flags and the applied actions."""
    flags, applied = [], []
    for _ in range(steps):
        out, flag = state.apply(action, {"ee_target": X})
        flags.append(flag)
        applied.append(out)
        X = apply_action(X, out)[0]
    return flags, np.stack(applied)


def test_the_miss_waits_for_the_descent_then_closes_the_hand_beside_its_heading_once():
    settings = MissedGrasps(start_z=(0.1, 0.1), offset=(0.04, 0.04), along=0.0, turn=(0.5, 0.5))
    miss = settings.start(np.random.default_rng(0))
    yaw = 0.3
    assert miss.apply(DOWN, {"ee_target": tcp_pose([0.5, 0.0, 0.15], yaw)}) == (DOWN, False)  # above
    level = DOWN * [1, 1, 0, 1, 1, 1, 1]
    assert miss.apply(level, {"ee_target": tcp_pose([0.5, 0.0, 0.09], yaw)})[1] is False  # not coming down
    start = tcp_pose([0.5, 0.0, 0.09], yaw)
    flags, applied = _play(miss, start, DOWN, 80)
    closing = np.flatnonzero(applied[:, 6] <= 0.0)
    assert len(closing) == settings.close_steps
    assert flags == [True] * (closing[-1] + 1) + [False] * (79 - closing[-1])  # one miss per episode
    np.testing.assert_allclose(applied[closing, :6], 0.0)  # the hand holds still while it closes
    # Where it closed: close_z, 4 cm across the fingers' closing direction (sin yaw, -cos yaw), turned 0.5.
    at_close = start.copy()
    for action in applied[: closing[0]]:
        at_close = apply_action(at_close, action)[0]
    shift = at_close[:2, 3] - start[:2, 3]
    assert at_close[2, 3] == pytest.approx(settings.close_z, abs=1e-6)
    assert np.linalg.norm(shift) == pytest.approx(0.04, abs=1e-6)
    assert abs(shift @ np.array([np.sin(yaw), -np.cos(yaw)])) < 1e-6
    assert abs(applied[: closing[0], 5].sum()) == pytest.approx(0.5)
    np.testing.assert_allclose(applied[: closing[0], 3:5], 0.0)
    assert (applied[closing[-1] + 1:] == DOWN).all()  # then the expert's own actions


def test_no_miss_after_the_gripper_first_closes():
    miss = MissedGrasps(start_z=(0.1, 0.1)).start(np.random.default_rng(1))
    close = DOWN * [1, 1, 1, 1, 1, 1, -1]
    assert miss.apply(close, {"ee_target": tcp_pose([0.5, 0.0, 0.05], 0.0)})[1] is False
    assert not any(miss.apply(DOWN, {"ee_target": tcp_pose([0.5, 0.0, 0.05], 0.0)})[1] for _ in range(50))


def test_the_miss_needs_the_commanded_pose():
    miss = MissedGrasps().start(np.random.default_rng(2))
    with pytest.raises(ValueError, match="ee_target"):
        miss.apply(DOWN, {})


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"start_z": (0.2, 0.1)}, "start_z"), ({"offset": (0.05, 0.03)}, "offset"), ({"along": -0.01}, "along"),
     ({"turn": (0.0, 1.0)}, "turn"), ({"close_z": 0.2}, "close_z"), ({"speed": 0.0}, "speed"),
     ({"close_steps": 0}, "close_steps")],
)
def test_bad_missed_grasp_settings_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        MissedGrasps(**kwargs)


def test_a_missed_grasp_is_followed_by_the_expert_opening_rising_and_grasping_again(tmp_path):
    from trivla_drake.eval.collect import CollectConfig, collect

    out = tmp_path / "missed"
    summary = collect(
        CollectConfig(out=str(out), episodes_per_task=1, tasks=["lift_block"], image_size=32, missed_grasps=True),
        progress=False,
    )
    assert summary["per_task"] == {"lift_block": 1}
    episode = LeRobotReader(out).episodes[0]
    assert episode[MISSED_GRASPS_KEY] is True
    missed = episode[PERTURBED_FRAMES_KEY]
    assert missed == list(range(missed[0], missed[-1] + 1))
    frames = LeRobotReader(out).episode_frames(0)
    state, actions = np.asarray(frames["observation.state"]), np.asarray(frames["action"])
    tcp_z = np.asarray(frames["observation.tcp_pose"])[:, 2]
    width = state[:, 7] + state[:, 8]
    after = missed[-1] + 1
    assert width[after] < 0.01  # the fingers closed on nothing: a real miss
    # The recorded (expert's) answer right after it: the hand open, rising; it grasps again later and holds.
    assert (actions[after:after + 10, 6] > 0.0).all()
    assert tcp_z[after + 30] > tcp_z[after] + 0.02
    regrasp = after + int(np.flatnonzero(actions[after:, 6] <= 0.0)[0])
    assert width[-1] > 0.03 and tcp_z[-1] > tcp_z[regrasp] + 0.05
    samples = TrainingSamples(out, cameras=[])
    assert samples[missed[0]]["action_is_stale"][1:].all()
    assert not samples[after]["action_is_stale"].any()


def test_missed_grasps_cannot_be_combined_with_other_disturbances():
    from trivla_drake.eval.collect import CollectConfig

    with pytest.raises(ValueError, match="--yaw-twists and --missed-grasps"):
        CollectConfig(out="unused", episodes_per_task=1, yaw_twists=True, missed_grasps=True).validate()
    with pytest.raises(ValueError, match="--action-noise and --missed-grasps"):
        CollectConfig(out="unused", episodes_per_task=1, action_noise=1.0, missed_grasps=True).validate()
