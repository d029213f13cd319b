"""Linear probes of System 2/3 features: the ridge read-out, the scene rebuild it is scored against,
the feature sets it reads, and the CLI's errors."""

import numpy as np
import pytest

from trivla_drake.cli import main
from trivla_drake.data.lerobot import LeRobotReader
from trivla_drake.eval.feature_probe import (
    first_frame_block_positions,
    first_frame_features,
    first_frame_image_tokens,
    first_frames,
    ridge_probe,
)
from trivla_drake.tasks.scene import BLOCK_COLORS
from trivla_drake.train.synthetic import write_synthetic_dataset


def test_ridge_probe_finds_a_linear_code_and_not_noise():
    rng = np.random.default_rng(0)
    features = rng.normal(size=(120, 40))
    targets = features @ rng.normal(size=(40, 2)) + 0.01 * rng.normal(size=(120, 2))
    r2, rmse, ridge = ridge_probe(features, targets)
    assert r2.shape == (2,) and (r2 > 0.9).all() and (rmse < 0.5 * targets.std(0)).all() and ridge > 0
    r2_noise, _, _ = ridge_probe(features, rng.normal(size=(120, 2)))
    assert (r2_noise < 0.2).all()


@pytest.mark.parametrize(
    "features, targets, message",
    [
        (np.zeros(20), np.zeros((20, 2)), "features must be 2-D"),
        (np.zeros((20, 4)), np.zeros(20), "targets must be 2-D"),
        (np.zeros((20, 4)), np.zeros((19, 2)), "features has 20 rows but targets has 19"),
        (np.zeros((6, 4)), np.zeros((6, 2)), "folds"),
        (np.full((20, 4), np.nan), np.zeros((20, 2)), "finite"),
    ],
)
def test_ridge_probe_rejects_bad_input(features, targets, message):
    with pytest.raises(ValueError, match=message):
        ridge_probe(features, targets)


def test_block_positions_are_the_scene_the_demonstration_saw(tmp_path):
    """Rebuilt from the recorded task and seed, the instructed block is where the oracle grasped."""
    from trivla_drake.eval.collect import CollectConfig, collect

    collect(CollectConfig(out=str(tmp_path / "d"), episodes_per_task=1, tasks=["lift_block"], image_size=32),
            progress=False)
    reader = LeRobotReader(tmp_path / "d")
    positions = first_frame_block_positions(reader, [0])
    assert positions.shape == (1, 2 * len(BLOCK_COLORS))
    frames = reader.episode_frames(0)
    grasp = int(np.nonzero(frames["action"][:, 6] < 0)[0][0])
    color = reader.episodes[0]["trivla/params"][0]
    block = positions[0, 2 * BLOCK_COLORS.index(color) : 2 * BLOCK_COLORS.index(color) + 2]
    assert np.linalg.norm(frames["observation.tcp_pose"][grasp, :2] - block) < 0.02


def test_feature_sets_of_the_first_frames(saved, tmp_path):
    model, _ = saved
    data = write_synthetic_dataset(tmp_path / "d", episodes=3, length=6, image_size=16)
    reader = LeRobotReader(data)
    frames = first_frames(reader, [0, 1, 2])
    features = first_frame_features(model, frames, [reader.task_of(e) for e in range(3)], batch=2)
    names = sorted(features)
    assert any(n.startswith("System 2 image tokens") for n in names)
    assert any(n.startswith("System 2 Q_vl") for n in names)
    assert any(n.startswith("System 3 F_p") for n in names)
    assert any(n.startswith("pixels 32x32") for n in names)
    for name, values in features.items():
        assert values.shape[0] == 3 and np.isfinite(values).all(), name
    vl = model.vision_language
    tokens = vl.config.vision.image_size // vl.config.vision.patch_size
    image_tokens = int(tokens * tokens * vl.config.pixel_shuffle_ratio**2)
    q_vl = next(v for n, v in features.items() if n.startswith("System 2 Q_vl"))
    assert q_vl.shape[1] == image_tokens * vl.hidden_size
    both = first_frame_image_tokens(model, frames, batch=2)
    assert both.shape == (3, 2 * image_tokens, vl.hidden_size)
    flat_static = next(v for n, v in features.items() if n.startswith("System 2 image tokens"))
    np.testing.assert_allclose(both[:, :image_tokens].reshape(3, -1), flat_static, rtol=1e-4, atol=1e-5)


def test_probe_cli_errors_name_the_problem(saved, tmp_path, capsys):
    _, checkpoint = saved
    data = write_synthetic_dataset(tmp_path / "d", episodes=12, length=4, image_size=16)
    assert main(["probe", "--data", data, "--checkpoint", checkpoint, "--episodes", "5"]) == 2
    assert "--episodes must be at least 10" in capsys.readouterr().err
    assert main(["probe", "--data", data, "--checkpoint", checkpoint, "--attention-steps", "-1"]) == 2
    assert "--attention-steps must be at least 0 and at most 100000" in capsys.readouterr().err
    assert main(["probe", "--data", data, "--checkpoint", checkpoint]) == 2
    assert "not written by `collect`" in capsys.readouterr().err
    assert main(["probe", "--data", str(tmp_path / "missing"), "--checkpoint", checkpoint]) == 2


def test_probe_table_has_the_ridge_and_attention_rows(saved, tmp_path, monkeypatch):
    """Every feature set gets a ridge row and System 2's image tokens two attention rows (without and
    with token positions); --attention-steps 0 leaves those out."""
    from trivla_drake.eval import feature_probe

    model, _ = saved
    data = write_synthetic_dataset(tmp_path / "d", episodes=12, length=4, image_size=16)
    rng = np.random.default_rng(0)
    monkeypatch.setattr(feature_probe, "first_frame_block_positions",
                        lambda reader, episodes: rng.normal(size=(len(episodes), 2 * len(BLOCK_COLORS))))
    results = feature_probe.probe_block_positions(model, LeRobotReader(data), attention_steps=3)
    attention = [r for r in results if "attention read-out" in r.feature]
    assert len(attention) == 2 and "no token positions" in attention[0].feature
    assert "+ token positions" in attention[1].feature
    assert all(len(r.rmse) == 2 * len(BLOCK_COLORS) and np.isfinite(r.rmse).all() for r in results)
    table = feature_probe.format_probe_table(results, 12)
    assert table.count("\n| System 2 image tokens, both views, attention") == 2
    plain = feature_probe.probe_block_positions(model, LeRobotReader(data), attention_steps=0)
    assert len(plain) == len(results) - 2
