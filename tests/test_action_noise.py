"""DART collection: perturbation bursts, their record in the data set, and the masked chunk labels."""

from __future__ import annotations

import numpy as np
import pytest

from trivla_drake.data.lerobot_format import PERTURBED_FRAMES_KEY, vector_feature
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.data.samples import TrainingSamples, perturbed_counts
from trivla_drake.eval.action_noise import PerturbationBursts
from trivla_drake.eval.plugin_config import PluginConfig


def test_bursts_disturb_motion_only_for_their_length():
    bursts = PerturbationBursts(rate=1.0, min_steps=3, max_steps=3).start(np.random.default_rng(0))
    action = np.array([0.001, 0.0, -0.002, 0.0, 0.0, 0.01, -1.0])
    out = [bursts.apply(action) for _ in range(3)]
    assert all(flag for _, flag in out)
    deltas = [applied - action for applied, _ in out]
    np.testing.assert_allclose(deltas[0], deltas[2])  # one constant velocity per burst
    assert 0.002 <= np.linalg.norm(deltas[0][:3]) <= 0.005
    assert all(applied[6] == -1.0 for applied, _ in out)  # the gripper is never disturbed
    assert not np.shares_memory(out[0][0], action) and action[0] == 0.001  # the expert's action is untouched


def test_zero_rate_never_disturbs():
    bursts = PerturbationBursts.scaled(0.0).start(np.random.default_rng(1))
    action = np.zeros(7)
    assert not any(bursts.apply(action)[1] for _ in range(500))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"rate": 1.5}, "rate"), ({"min_steps": 5, "max_steps": 2}, "min_steps"), ({"speed": (0.01, 0.0)}, "speed")],
)
def test_bad_burst_settings_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        PerturbationBursts(**kwargs)


def _dart(scale: float) -> PluginConfig:
    return PluginConfig("dart", {"scale": scale})


def test_bad_perturbations_are_clear_errors_naming_the_field():
    from trivla_drake.eval.collect import CollectConfig

    for bad in (-1.0, 100.0, float("nan")):
        with pytest.raises(ValueError, match=r"perturbation \(dart\): scale must be in \[0, "):
            CollectConfig(out="unused", episodes_per_task=1, perturbation=_dart(bad)).validate()
    with pytest.raises(ValueError, match=r"perturbation \(dart\): settings of the perturbation 'dart': .*'rate'"):
        CollectConfig(out="unused", episodes_per_task=1, perturbation=PluginConfig("dart", {"rate": 1.0})).validate()
    with pytest.raises(ValueError, match="perturbation.settings .* without a perturbation.name"):
        CollectConfig(out="unused", episodes_per_task=1, perturbation=PluginConfig("", {"scale": 1.0})).validate()
    with pytest.raises(ValueError, match="unknown perturbation 'dartt'"):
        CollectConfig(out="unused", episodes_per_task=1, perturbation=PluginConfig("dartt")).validate()


def test_perturbed_counts():
    np.testing.assert_array_equal(perturbed_counts([1, 2], 4), [0, 0, 1, 2, 2])
    with pytest.raises(ValueError, match="perturbed frame"):
        perturbed_counts([4], 4)


def test_chunk_entries_after_a_disturbed_step_are_stale(tmp_path):
    features = {"observation.state": vector_feature(["s"]), "action": vector_feature([f"a{i}" for i in range(7)])}
    writer = LeRobotWriter(tmp_path / "ds", fps=36.0, features=features)
    frames = {"observation.state": np.zeros((12, 1), np.float32), "action": np.zeros((12, 7), np.float32)}
    writer.add_episode(frames, "clean")
    writer.add_episode(frames, "noisy", extra={PERTURBED_FRAMES_KEY: [3, 4]})
    samples = TrainingSamples(LeRobotReader(tmp_path / "ds"), history=1, future_frames=0, chunk_size=4, cameras=[])
    assert not any(samples[i]["action_is_stale"].any() for i in range(12))
    stale = {t: samples[12 + t]["action_is_stale"].tolist() for t in range(12)}
    assert stale[0] == [False] * 4  # frames 0..2 are not disturbed
    assert stale[1] == [False, False, False, True]  # entry 3 comes after step 3
    assert stale[3] == [False, True, True, True]  # the expert's answer to frame 3 itself is a label
    assert stale[5] == [False] * 4  # the burst is over


def test_noisy_collection_records_disturbed_frames(tmp_path):
    from trivla_drake.eval.collect import CollectConfig, collect

    out = tmp_path / "dart"
    summary = collect(
        CollectConfig(out=str(out), episodes_per_task=1, tasks=["turn_on_light"], image_size=32,
                      perturbation=_dart(3.0)),
        progress=False,
    )
    assert summary["per_task"] == {"turn_on_light": 1}
    episode = LeRobotReader(out).episodes[0]
    assert episode["trivla/action_noise"] == 3.0
    disturbed = episode[PERTURBED_FRAMES_KEY]
    assert len(disturbed) > 0 and max(disturbed) < episode["length"]
    samples = TrainingSamples(out, cameras=[])
    assert any(samples[t]["action_is_stale"].any() for t in disturbed)


def test_dart_is_a_registered_perturbation_and_an_unknown_name_lists_the_registered_ones():
    """`make_perturbation("dart", scale=x)` is collect's perturbation {name: dart, settings: {scale: x}}; a name not registered is refused, naming
    the registered ones; a name registered twice is refused."""
    from trivla_drake.eval.collect import CollectConfig
    from trivla_drake.eval.perturbations import PERTURBATIONS, make_perturbation, register_perturbation

    assert make_perturbation("dart", scale=2.0) == PerturbationBursts.scaled(2.0)
    assert CollectConfig(out="unused", episodes_per_task=1, perturbation=_dart(2.0)).disturbance() == make_perturbation(
        "dart", scale=2.0)
    assert CollectConfig(out="unused", episodes_per_task=1).disturbance() is None
    assert CollectConfig(out="unused", episodes_per_task=1, perturbation=_dart(0.0)).disturbance() is None
    with pytest.raises(ValueError, match=r"unknown perturbation 'dartt'; registered: .*dart"):
        make_perturbation("dartt")
    with pytest.raises(ValueError, match="'dart' is registered already"):
        register_perturbation("dart")(lambda: None)
    assert "dart" in PERTURBATIONS.names()


def test_run_episode_takes_one_perturbation_object():
    """A perturbation (what the registry makes) disturbs the applied actions of an episode and marks those frames."""
    from trivla_drake.eval.episode import run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    result = run_episode("turn_on_light", 0, OraclePolicy(), keep_trajectory=True, max_steps=5,
                         perturbation=PerturbationBursts(rate=1.0, min_steps=1, max_steps=1))
    assert len(result.trajectory.perturbed) == 5 and all(result.trajectory.perturbed)
