"""Bad inputs to `trivla-drake train` give one clear error line (exit code 2) before any training:
a truncated checkpoint, one of another preset or another action space, a corrupt resume state, a
folder that is not a dataset."""

from __future__ import annotations

import dataclasses
import os

import pytest

from trivla_drake.nn import TriVLA, make_config, save_checkpoint
from trivla_drake.train.cli_commands import add_train_parser, main, train_config_from_args
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.synthetic import write_synthetic_dataset


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("errors")
    data = write_synthetic_dataset(root / "data", episodes=1, length=8, image_size=16)
    good = root / "tiny"
    save_checkpoint(TriVLA(make_config("tiny")), str(good))
    return {"root": root, "data": data, "good": str(good), "cache": str(root / "cache")}


def _train(setup, out, *extra):
    args = ["train", "--stage", "policy", "--data", setup["data"], "--out", str(out), "--steps", "2",
            "--set", "batch_size=2", "--set", f"cache_dir={setup['cache']}", "--no-progress", *extra]
    return main(args)


def _fails_before_training(setup, capsys, out, *extra) -> str:
    assert _train(setup, out, *extra) == 2
    err = capsys.readouterr().err
    assert err.startswith("trivla-drake train: error: ") and err.count("\n") == 1, err
    assert not (out / "checkpoints").exists() and not (out / "final").exists()
    return err


def test_truncated_init_checkpoint(setup, capsys, tmp_path):
    bad = tmp_path / "truncated"
    bad.mkdir()
    for name in ("config.json", "model.safetensors"):
        content = open(os.path.join(setup["good"], name), "rb").read()
        (bad / name).write_bytes(content[: len(content) // 2] if name == "model.safetensors" else content)
    err = _fails_before_training(setup, capsys, tmp_path / "out", "--init", str(bad))
    assert "truncated or corrupt" in err


def test_init_checkpoint_of_another_preset(setup, capsys, tmp_path):
    err = _fails_before_training(setup, capsys, tmp_path / "out", "--init", setup["good"], "--preset", "cpu")
    assert "preset 'tiny'" in err and "another preset" in err


def test_init_checkpoint_of_another_action_space(setup, capsys, tmp_path):
    config = make_config("tiny")
    six = dataclasses.replace(config, policy=dataclasses.replace(config.policy, action_dim=6),
                              action_names=config.action_names[:6])
    other = tmp_path / "six_dof"
    save_checkpoint(TriVLA(six), str(other))
    err = _fails_before_training(setup, capsys, tmp_path / "out", "--init", str(other))
    assert "6-D action space" in err and "7-D 'action'" in err and "another action space" in err


def test_resume_with_another_preset_or_a_corrupt_state(setup, capsys, tmp_path):
    out = tmp_path / "run"
    assert _train(setup, out, "--preset", "tiny", "--set", "checkpoint_every=1") == 0
    capsys.readouterr()
    assert _train(setup, out, "--preset", "cpu", "--resume", "--steps", "3") == 2
    assert "cannot resume: preset was 'tiny'" in capsys.readouterr().err
    state = out / "final" / "training_state.pt"
    state.write_bytes(state.read_bytes()[:100])
    # A truncated newest checkpoint is skipped, said, and kept: the run resumes from the newest intact one.
    assert _train(setup, out, "--resume", "--steps", "3") == 0
    err = capsys.readouterr().err
    assert "training_state.pt is truncated or corrupt" in err and "resuming from the newest intact one" in err
    assert (out / "final.unreadable" / "training_state.pt").stat().st_size == 100


def test_not_a_dataset_and_a_missing_init(setup, capsys, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["train", "--stage", "video", "--data", str(empty), "--out", str(tmp_path / "o"),
                 "--preset", "tiny", "--no-progress"]) == 2
    assert "is not a LeRobot dataset" in capsys.readouterr().err
    err = _fails_before_training(setup, capsys, tmp_path / "out", "--init", str(tmp_path / "nowhere"))
    assert "not a checkpoint directory" in err


def test_parser_maps_every_flag_and_setting_to_the_config(tmp_path):
    """The direct flags, then --config, then --set (in order), land in their dotted fields; flags win."""
    import argparse

    parser = argparse.ArgumentParser()
    add_train_parser(parser.add_subparsers(dest="command"))
    file = tmp_path / "policy.yaml"
    file.write_text("stage: video\nlr: 0.25\noptimizer:\n  beta2: 0.99\npolicy:\n  grounding:\n    weight: 2\n")
    args = parser.parse_args(["train", "--stage", "policy", "--data", "d", "--out", "o", "--preset", "cpu",
                              "--init", "i", "--steps", "7", "--resume", "--seed", "9", "--threads", "1",
                              "--no-progress", "--config", str(file), "--set", "lr=0.5", "--set", "batch_size=3",
                              "--set", "use_system2=false", "--set", "policy.grounding.phase=bind",
                              "--set", "policy.grounding.carry_tasks=[stack_block]", "--set", "optimizer.grad_clip=0"])
    config = train_config_from_args(args)
    assert (config.stage, config.data, config.out, config.preset, config.init) == ("policy", "d", "o", "cpu", "i")
    assert (config.steps, config.batch_size, config.lr, config.seed, config.threads) == (7, 3, 0.5, 9, 1)
    assert config.resume and not config.progress and not config.use_system2
    assert (config.policy.grounding.weight, config.policy.grounding.phase) == (2.0, "bind")
    assert config.policy.grounding.carry_tasks == ["stack_block"]
    assert (config.optimizer.beta2, config.optimizer.grad_clip, config.optimizer.warmup_steps) == (0.99, 0.0, 100)
    defaults = train_config_from_args(parser.parse_args(["train", "--stage", "policy", "--out", "o"]))
    assert defaults == dataclasses.replace(TrainConfig(), stage="policy", out="o")


def test_a_setting_that_is_no_field_is_named(capsys, tmp_path):
    assert main(["train", "--stage", "policy", "--out", str(tmp_path / "o"), "--set", "policy.grounding.phse=bind"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trivla-drake train: error: --set policy.grounding.phse=bind") and "'phase'" in err


@pytest.mark.parametrize("dotted, value, message", [
    ("optimizer.warmup_steps", -1, "optimizer.warmup_steps must be >= 0"),
    ("optimizer.grad_clip", -0.5, "optimizer.grad_clip must be >= 0"),
    ("optimizer.weight_decay", float("nan"), "optimizer.weight_decay must be >= 0"),
    ("optimizer.beta2", 1.0, r"optimizer.beta2 must be in \[0, 1\)"),
    ("optimizer.beta1", -0.1, r"optimizer.beta1 must be in \[0, 1\)"),
    ("optimizer.min_lr_ratio", 1.5, r"optimizer.min_lr_ratio must be in \[0, 1\]"),
    ("features.dtype", "float8", "features.dtype must be one of float16, bfloat16, float32; got 'float8'"),
    ("policy.grounding.phase", "glue", "policy.grounding.phase must be one of joint, bind, follow"),
    ("policy.grounding.lr_scale", 0.0, "policy.grounding.lr_scale must be a finite number > 0"),
])
def test_settings_out_of_range_are_named_by_their_dotted_field(dotted, value, message, tmp_path):
    from trivla_drake.config_io import with_flags

    config = with_flags(TrainConfig(stage="policy", data="d", out=str(tmp_path / "o")), {dotted: value})
    with pytest.raises(ValueError, match=message):
        config.resolved().validate()


@pytest.mark.parametrize("stage, dotted, value", [
    ("vlm", "features.stride", 3), ("video", "policy.grounding.weight", 1.0), ("policy", "vlm.dense_weight", 1.0),
    ("policy", "video.clip_seconds", 2.0), ("vlm", "policy.vl_position_embedding", True),
])
def test_a_setting_of_another_stage_is_refused_naming_field_and_stage(stage, dotted, value):
    from trivla_drake.config_io import with_flags

    config = with_flags(TrainConfig(stage=stage, data="d", out="o"), {dotted: value})
    with pytest.raises(ValueError, match=rf"{dotted} \({value!r}\) is a setting of the \w+ stage; this run is the "
                                         rf"{stage} stage"):
        config.resolved().validate()


def test_a_resume_that_changes_a_setting_names_its_dotted_field():
    from trivla_drake.config_io import with_flags
    from trivla_drake.train.config import check_resume_compatible

    saved = TrainConfig(stage="policy", data="d", out="o")
    with pytest.raises(ValueError, match=r"cannot resume: policy.grounding.lr_scale was 3.0 in the run being resumed, "
                                         r"now 0.5"):
        check_resume_compatible(saved, with_flags(saved, {"policy.grounding.lr_scale": 0.5}))
    check_resume_compatible(saved, with_flags(saved, {"steps": 9, "vlm.vqa_eval_questions": 3, "out": "p"}))


@pytest.mark.parametrize("extra, message", [
    (("--set", "policy.grounding.carry_tasks=[stack_blok]", "--set", "policy.grounding.weight=1"),
     r"policy.grounding.carry_tasks names unknown tasks \['stack_blok'\]"),
    (("--set", "policy.grounding.carry_tasks=[stack_block]"),
     r"policy.grounding.carry_tasks works on System 1's instruction grounding: it needs policy.grounding.weight > 0"),
])
def test_grounding_carry_names_a_bad_task_or_a_missing_grounding(setup, capsys, tmp_path, extra, message):
    import re

    err = _fails_before_training(setup, capsys, tmp_path / "out", "--init", setup["good"], *extra)
    assert re.search(message, err), err


def flat_train_config(config: TrainConfig) -> dict:
    """`config` as the flat train_config.json of before the nested TrainConfig held it (the old field names)."""
    from trivla_drake.train.config import FLAT_FIELD_PATHS

    old_name = {dotted: name for name, dotted in FLAT_FIELD_PATHS.items()}

    def leaves(section, prefix):
        for f in dataclasses.fields(section):
            value = getattr(section, f.name)
            if dataclasses.is_dataclass(value):
                yield from leaves(value, f"{prefix}{f.name}.")
            else:
                yield old_name.get(f"{prefix}{f.name}", f"{prefix}{f.name}"), value

    return dict(leaves(config, ""))


def test_a_flat_training_config_of_before_reads_as_the_nested_one():
    """A checkpoint written before the nested config holds a flat train_config.json: it reads (every old field lands
    in its dotted place), options that left at their shipped value are ignored, one turned on is refused naming
    the field and the git tag with its code."""
    from trivla_drake.config_io import with_flags
    from trivla_drake.train.config import REMOVED_FIELDS

    config = with_flags(TrainConfig(stage="policy", data="d", out="o"), {
        "features.stride": 3, "policy.grounding.weight": 1.0, "policy.grounding.carry_tasks": ["stack_block"],
        "optimizer.beta2": 0.999, "vlm.vqa_seed": 2, "video.clip_seconds": 0.5, "policy.subgoal_offset": True})
    flat = flat_train_config(config)
    assert len(flat) == 67 - len(REMOVED_FIELDS) and "grounding_carry_tasks" in flat and "features" not in flat
    assert TrainConfig.from_dict({**flat, **REMOVED_FIELDS}) == config
    with pytest.raises(ValueError, match=r"training config\.subgoal_noise is 0\.02.*research-archive"):
        TrainConfig.from_dict({**flat, "subgoal_noise": 0.02})
    with pytest.raises(ValueError, match=r"TrainConfig has no fields \['no_such_option'\]"):
        TrainConfig.from_dict({**flat, "no_such_option": 1})
