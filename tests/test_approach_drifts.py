"""Approach drifts (`collect --approach-drifts`): once per episode, on the open hand's way down to its
first grasp, the applied actions push it sideways and turn it at a constant height; the expert with
`align_first` stops going down, centres the hand above the block again and turns back, then grasps.
Collect records the disturbed frames, so their later chunk entries are no labels. Undisturbed,
`align_first` changes nothing. Bad settings are refused naming the field."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.data.lerobot import APPROACH_DRIFTS_KEY, PERTURBED_FRAMES_KEY, LeRobotReader
from trivla_drake.data.samples import TrainingSamples
from trivla_drake.eval.approach_drifts import ApproachDrifts
from trivla_drake.systems.action_executor import apply_action
from trivla_drake.tasks.scene import hand_yaw, tcp_pose

DOWN = np.array([0.0, 0.0, -0.003, 0.0, 0.0, 0.0, 1.0])


def test_the_drift_waits_for_the_descent_then_moves_across_and_turns_at_its_height_once():
    settings = ApproachDrifts(start_z=(0.1, 0.1), offset=(0.03, 0.03), turn=(0.5, 0.5))
    drift = settings.start(np.random.default_rng(0))
    assert drift.apply(DOWN, {"ee_target": tcp_pose([0.5, 0.0, 0.15], 0.2)}) == (DOWN, False)  # above
    level = DOWN * [1, 1, 0, 1, 1, 1, 1]
    assert drift.apply(level, {"ee_target": tcp_pose([0.5, 0.0, 0.09], 0.2)})[1] is False  # not coming down
    start = X = tcp_pose([0.5, 0.0, 0.09], 0.2)
    flags = []
    for _ in range(60):
        applied, flag = drift.apply(DOWN, {"ee_target": X})
        flags.append(flag)
        if flag:
            X = apply_action(X, applied)[0]
            assert applied[6] > 0.0  # the hand stays open
    assert flags == [True] * drift.steps + [False] * (60 - drift.steps)  # one drift per episode
    assert X[2, 3] == pytest.approx(start[2, 3], abs=1e-9)  # at its height
    assert np.linalg.norm(X[:2, 3] - start[:2, 3]) == pytest.approx(0.03, abs=1e-6)
    assert abs(hand_yaw(X) - hand_yaw(start)) == pytest.approx(0.5, abs=1e-6)


def test_no_drift_after_the_gripper_first_closes():
    drift = ApproachDrifts(start_z=(0.1, 0.1)).start(np.random.default_rng(1))
    close = DOWN * [1, 1, 1, 1, 1, 1, -1]
    assert drift.apply(close, {"ee_target": tcp_pose([0.5, 0.0, 0.05], 0.0)})[1] is False
    assert not any(drift.apply(DOWN, {"ee_target": tcp_pose([0.5, 0.0, 0.05], 0.0)})[1] for _ in range(50))


def test_the_drift_needs_the_commanded_pose():
    with pytest.raises(ValueError, match="ee_target"):
        ApproachDrifts().start(np.random.default_rng(2)).apply(DOWN, {})


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"start_z": (0.2, 0.1)}, "start_z"), ({"offset": (0.0, 0.03)}, "offset"), ({"turn": (0.0, 1.0)}, "turn"),
     ({"speed": 0.0}, "speed"), ({"speed": 1.0}, "speed")],
)
def test_bad_approach_drift_settings_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        ApproachDrifts(**kwargs)


def test_align_first_changes_nothing_without_a_disturbance():
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    runs = [run_episode("lift_block", 5, OraclePolicy(align_first=flag), keep_trajectory=True) for flag in (False, True)]
    assert all(r.success for r in runs)
    np.testing.assert_array_equal(np.stack(runs[0].trajectory.actions), np.stack(runs[1].trajectory.actions))


def test_a_drifted_approach_is_centred_again_by_the_expert_before_it_goes_on_down(tmp_path):
    from trivla_drake.eval.collect import CollectConfig, collect
    from trivla_drake.tasks.oracle import ALIGN_FIRST_M

    out = tmp_path / "drifted"
    summary = collect(
        CollectConfig(out=str(out), episodes_per_task=1, tasks=["lift_block"], image_size=32, approach_drifts=True),
        progress=False,
    )
    assert summary["per_task"] == {"lift_block": 1}
    reader = LeRobotReader(out)
    episode = reader.episodes[0]
    assert episode[APPROACH_DRIFTS_KEY] is True
    drifted = episode[PERTURBED_FRAMES_KEY]
    assert drifted == list(range(drifted[0], drifted[-1] + 1))
    frames = reader.episode_frames(0)
    actions = np.asarray(frames["action"])
    tcp = np.asarray(frames["observation.tcp_pose"])
    close = int(np.flatnonzero(actions[:, 6] <= 0.0)[0])
    after = drifted[-1] + 1
    # The drift took the hand off where it closes; the expert's recorded answer first goes back across
    # without going down, and the close is centred again.
    assert np.linalg.norm(tcp[after, :2] - tcp[close, :2]) > 0.01
    assert np.linalg.norm(tcp[close, :2] - tcp[drifted[0], :2]) < 2 * ALIGN_FIRST_M
    across = actions[after, :2] @ (tcp[close, :2] - tcp[after, :2])
    assert across > 0.0 and actions[after, 2] == 0.0
    samples = TrainingSamples(out, cameras=[])
    assert samples[drifted[0]]["action_is_stale"][1:].all()
    assert not samples[after]["action_is_stale"].any()


def test_approach_drifts_cannot_be_combined_with_other_disturbances():
    from trivla_drake.eval.collect import CollectConfig

    with pytest.raises(ValueError, match="--missed-grasps and --approach-drifts"):
        CollectConfig(out="unused", episodes_per_task=1, missed_grasps=True, approach_drifts=True).validate()
