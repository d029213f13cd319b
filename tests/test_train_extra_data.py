"""`train`'s extra_data: the policy stage trains on several LeRobot datasets together, each episode once,
with the normalisation of all of them, and refuses folders it cannot join with an error naming the field."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import yaml

from trivla_drake.config_io import with_flags
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.data.lerobot_stats import aggregate_stats, episode_stats
from trivla_drake.nn import load_checkpoint
from trivla_drake.train import TrainConfig, train
from trivla_drake.train.cli_commands import main
from trivla_drake.train.dataset_union import PolicyDatasetUnion, drop_repeated_episodes, episode_row_key
from trivla_drake.train.synthetic import write_synthetic_dataset


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """a: 3 episodes; b: 5 episodes of the same seed (its first 3 are a's); c: other episodes at 18 fps;
    posed: other episodes with tcp poses."""
    root = tmp_path_factory.mktemp("extra")
    a = write_synthetic_dataset(root / "a", episodes=3, length=20, image_size=16)
    b = write_synthetic_dataset(root / "b", episodes=5, length=20, image_size=16)
    c = write_synthetic_dataset(root / "c", episodes=2, length=20, image_size=16, fps=18.0, seed=3)
    posed = write_synthetic_dataset(root / "posed", episodes=2, length=20, image_size=16, seed=5, tcp_pose=True)
    return {"root": root, "a": a, "b": b, "c": c, "posed": posed, "cache": str(root / "cache")}


class _MovedReader:
    """A reader whose episode rows are another's, stored elsewhere (other indices, files and offsets)."""

    def __init__(self, reader: LeRobotReader, shift: int):
        self.episodes = []
        for row in reader.episodes:
            moved = dict(row)
            moved["episode_index"] = row["episode_index"] + shift
            moved["dataset_from_index"] = row["dataset_from_index"] + 100 * shift
            moved["data/file_index"] = row["data/file_index"] + 1
            moved["stats/index/min"] = [v + 100 * shift for v in row["stats/index/min"]]
            self.episodes.append(moved)


def test_an_episode_stored_elsewhere_keeps_its_row_key_and_other_content_changes_it(folders):
    a = LeRobotReader(folders["a"])
    moved = _MovedReader(a, shift=7)
    assert [episode_row_key(moved, e) for e in range(3)] == [episode_row_key(a, e) for e in range(3)]
    assert len({episode_row_key(a, e) for e in range(3)}) == 3
    moved.episodes[1]["stats/action/mean"] = [v + 1e-3 for v in moved.episodes[1]["stats/action/mean"]]
    assert episode_row_key(moved, 1) != episode_row_key(a, 1)


def test_repeated_episodes_are_kept_once_in_the_first_folder(folders):
    a, b = LeRobotReader(folders["a"]), LeRobotReader(folders["b"])
    kept, dropped = drop_repeated_episodes([a, b], [[0, 1, 2], [0, 1, 2, 3, 4]])
    assert kept == [[0, 1, 2], [3, 4]] and dropped == 3
    kept, dropped = drop_repeated_episodes([b, a], [[1, 3], [0, 1, 2]])
    assert kept == [[1, 3], [0, 2]] and dropped == 1
    kept, dropped = drop_repeated_episodes([a, a], [[0, 0, 2], [2]])  # repeats inside one folder stay
    assert kept == [[0, 0, 2], []] and dropped == 1


def test_union_samples_run_through_each_part_in_order():
    class Part:
        def __init__(self, name, n):
            self.name, self.n, self.shards = name, n, {0: f"{name}.safetensors"}

        def __len__(self):
            return self.n

        def __getitem__(self, i):
            return (self.name, i)

    union = PolicyDatasetUnion([Part("a", 2), Part("b", 3)])
    assert len(union) == 5 and [union[i] for i in range(5)] == [("a", 0), ("a", 1), ("b", 0), ("b", 1), ("b", 2)]
    assert union.shards == {(0, 0): "a.safetensors", (1, 0): "b.safetensors"}
    with pytest.raises(IndexError):
        union[5]
    with pytest.raises(AssertionError):  # torch's message: "datasets should not be an empty iterable"
        PolicyDatasetUnion([])


def test_policy_stage_trains_on_both_folders_with_their_joint_normalisation(folders):
    out = folders["root"] / "run"
    summary = train(with_flags(TrainConfig(stage="policy", data=folders["a"], extra_data=[folders["b"]], out=str(out),
                                           preset="tiny", steps=3, batch_size=4, cache_dir=folders["cache"], progress=False), {"features.stride": 2}))
    assert summary["episodes"] == 5 and summary["repeated_episodes_dropped"] == 3
    assert summary["episodes_per_dataset"] == {folders["a"]: 3, folders["b"]: 2}
    assert summary["samples"] == 5 * 10  # every second frame of 5 episodes of 20 frames
    assert summary["feature_shards_computed"] == 5  # a's three and b's two new episodes, each once
    a, b = LeRobotReader(folders["a"]), LeRobotReader(folders["b"])
    both = aggregate_stats([a.stats, *(episode_stats(b.episodes[e]) for e in (3, 4))])  # b's 0-2 are a's
    model = load_checkpoint(summary["final_checkpoint"])
    assert np.allclose(model.normalization.state_mean, both["observation.state"]["mean"], atol=1e-6)
    # ... which --data's statistics alone would not give (b's own equal the union here: its 0-2 are a's).
    assert not np.allclose(model.normalization.state_mean, a.stats["observation.state"]["mean"], atol=1e-4)
    assert np.allclose(model.normalization.action_max, both["action"]["max"], atol=1e-6)
    saved = yaml.safe_load((out / "final" / "train_config.yaml").read_text())
    assert saved["extra_data"] == [folders["b"]] and saved["features"]["stride"] == 2


@pytest.mark.parametrize("extra, message", [
    (["--stage", "video", "--set", "extra_data=[B]"], "extra_data applies to the policy stage only"),
    (["--set", "extra_data=[C]"], "is recorded at 18.0 fps"),
    (["--set", "extra_data=[A]"], "which is already data: each folder once"),
    (["--set", "extra_data=[C, C]"], "which is already given: each folder once"),
    (["--set", "extra_data=[POSED]"], "has ['observation.tcp_pose'] that --data lacks"),
])
def test_folders_that_cannot_be_joined_are_refused_before_training(folders, capsys, tmp_path, extra, message):
    named = {"A": folders["a"], "B": folders["b"], "C": folders["c"], "POSED": folders["posed"]}
    for name, folder in named.items():
        extra = [word.replace(name, folder) if word.startswith("extra_data=") else word for word in extra]
    args = ["train", "--stage", "policy", "--data", folders["a"], "--out", str(tmp_path / "out"), "--steps", "2",
            "--preset", "tiny", "--set", f"cache_dir={folders['cache']}", "--no-progress", *extra]
    assert main(args) == 2
    err = capsys.readouterr().err
    error = err.strip().splitlines()[-1]  # after any note
    assert error.startswith("trivla-drake train: error: ") and message in error, err
    assert not (tmp_path / "out" / "final").exists()


def _edited_copy(source: str, target, edit) -> str:
    """A copy of dataset `source` at `target` whose meta/info.json `edit` changed in place."""
    import shutil

    shutil.copytree(source, target)
    info_path = target / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    edit(info["features"])
    info_path.write_text(json.dumps(info))
    return str(target)


def _renamed_action(features):
    features["action"]["names"] = [*features["action"]["names"][:-1], "gripper_width"]


def _renamed_wrist_camera(features):
    features["observation.images.hand"] = features.pop("observation.images.wrist")


@pytest.mark.parametrize("edit, message", [
    (_renamed_action, "another action space"),
    (_renamed_wrist_camera, "has no camera 'observation.images.wrist'"),
])
def test_an_extra_folder_of_another_space_or_cameras_is_refused_naming_it(folders, capsys, tmp_path, edit, message):
    extra = _edited_copy(folders["b"], tmp_path / "edited", edit)
    args = ["train", "--stage", "policy", "--data", folders["a"], "--set", f"extra_data=[{extra}]", "--out",
            str(tmp_path / "out"), "--steps", "2", "--preset", "tiny", "--set", f"cache_dir={folders['cache']}",
            "--no-progress"]
    assert main(args) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in error and extra in error, error
    assert not (tmp_path / "out" / "final").exists()
    assert LeRobotReader(folders["b"]).features["action"]["names"][-1] == "gripper"  # the source is untouched


def test_a_grounded_run_refuses_an_extra_folder_without_tcp_poses(folders, tmp_path):
    posed = write_synthetic_dataset(tmp_path / "posed", episodes=2, length=20, image_size=16, tcp_pose=True)
    common = dict(stage="policy", preset="tiny", steps=1, batch_size=4, cache_dir=folders["cache"], progress=False)
    missing = "'observation.tcp_pose', which dataset " + re.escape(folders["b"]) + " does not have"
    with pytest.raises(ValueError, match=missing):
        train(with_flags(TrainConfig(data=posed, extra_data=[folders["b"]], out=str(tmp_path / "out"), **common),
                         {"features.stride": 2, "policy.grounding.weight": 0.5}))
    assert not (tmp_path / "out" / "final").exists()


def test_an_extra_folder_that_adds_nothing_new_is_refused_before_any_caching(folders, tmp_path):
    """data b, extra_data [a]: all of a's episodes are b's first three (a copy given by mistake)."""
    cache = tmp_path / "cache"
    with pytest.raises(ValueError, match=r"extra_data: dataset .*/a adds no episode"):
        train(TrainConfig(stage="policy", data=folders["b"], extra_data=(folders["a"],), out=str(tmp_path / "out"),
                          preset="tiny", steps=1, batch_size=4, cache_dir=str(cache), progress=False))
    assert not list(cache.rglob("*.safetensors"))


def test_a_resume_on_other_folders_is_refused_naming_them(folders, tmp_path):
    common = dict(stage="policy", data=folders["a"], out=str(tmp_path / "run"), preset="tiny", batch_size=4,
                  cache_dir=folders["cache"], progress=False, checkpoint_every=2)
    stride = {"features.stride": 2}
    train(with_flags(TrainConfig(steps=2, **common), stride))
    with pytest.raises(ValueError, match=r"data / extra_data give other statistics"):
        train(with_flags(TrainConfig(steps=4, resume=True, extra_data=[folders["b"]], **common), stride))
    resumed = train(with_flags(TrainConfig(steps=4, resume=True, **common), stride))  # the same folder resumes
    assert (resumed["resumed_from_step"], resumed["steps"]) == (2, 4)


def test_an_episode_keeps_its_row_key_whether_its_unused_settings_are_written_or_not():
    """Rows written before session 66 leave unused settings out; newer rows write their defaults: the same episode."""
    from trivla_drake.data.lerobot_format import EPISODE_COLUMN_DEFAULTS

    class Rows:
        def __init__(self, *rows):
            self.episodes = list(rows)

    old = {"episode_index": 0, "trivla/task": "lift_block", "trivla/seed": 7, "trivla/params": ["red"]}
    new = {**old, **EPISODE_COLUMN_DEFAULTS}
    other = {**new, "trivla/stacked_pick": True}
    keys = [episode_row_key(Rows(row), 0) for row in (old, new, other)]
    assert keys[0] == keys[1] != keys[2]
