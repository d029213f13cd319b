"""Bad inputs to `trivla-drake train` give one clear error line (exit code 2) before any training:
a truncated checkpoint, one of another preset or another action space, a corrupt resume state, a
folder that is not a dataset."""

from __future__ import annotations

import dataclasses
import os

import pytest

from trivla_drake.nn import TriVLA, make_config, save_checkpoint
from trivla_drake.train.cli_commands import add_train_parser, config_from_args, main
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
            "--batch-size", "2", "--cache-dir", setup["cache"], "--no-progress", *extra]
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
    assert _train(setup, out, "--preset", "tiny", "--checkpoint-every", "1") == 0
    capsys.readouterr()
    assert _train(setup, out, "--preset", "cpu", "--resume", "--steps", "3") == 2
    assert "cannot resume: preset (--preset) was 'tiny'" in capsys.readouterr().err
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


def test_parser_maps_every_flag_to_the_config():
    import argparse

    parser = argparse.ArgumentParser()
    add_train_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["train", "--stage", "policy", "--data", "d", "--out", "o", "--preset", "cpu",
                              "--init", "i", "--steps", "7", "--batch-size", "3", "--lr", "0.5",
                              "--checkpoint-every", "2", "--resume", "--seed", "9", "--workers", "1",
                              "--no-system2", "--no-system3",
                              "--vl-position-embedding", "--dense-weight", "0.5", "--grounding-weight", "0.25",
                              "--grounding-lr-scale", "2", "--grounding-phase", "bind", "--warmup-steps", "0",
                              "--min-lr-ratio", "1", "--beta2", "0.999", "--grad-clip", "0"])
    config = config_from_args(args)
    assert (config.stage, config.data, config.out, config.preset, config.init) == ("policy", "d", "o", "cpu", "i")
    assert (config.steps, config.batch_size, config.lr, config.checkpoint_every) == (7, 3, 0.5, 2)
    assert (config.resume, config.seed, config.workers) == (True, 9, 1)
    assert not config.use_system2 and not config.use_system3
    assert config.vl_position_embedding and config.dense_weight == 0.5 and config.grounding_weight == 0.25
    assert config.grounding_lr_scale == 2.0 and config.grounding_phase == "bind"
    assert (config.warmup_steps, config.min_lr_ratio, config.beta2, config.grad_clip) == (0, 1.0, 0.999, 0.0)
    defaults = config_from_args(parser.parse_args(["train", "--stage", "policy", "--out", "o"]))
    assert (defaults.warmup_steps, defaults.min_lr_ratio, defaults.beta2, defaults.grad_clip) == (100, 0.1, 0.95, 1.0)


@pytest.mark.parametrize("field, value, message", [
    ("warmup_steps", -1, "warmup_steps \\(--warmup-steps\\) must be >= 0"),
    ("grad_clip", -0.5, "grad_clip \\(--grad-clip\\) must be >= 0"),
    ("weight_decay", float("nan"), "weight_decay must be >= 0"),
    ("beta2", 1.0, r"beta2 \(--beta2\) must be in \[0, 1\)"),
    ("beta1", -0.1, r"beta1 must be in \[0, 1\)"),
    ("min_lr_ratio", 1.5, r"min_lr_ratio \(--min-lr-ratio\) must be in \[0, 1\]"),
])
def test_optimizer_settings_out_of_range_are_named(field, value, message, tmp_path):
    from trivla_drake.train.config import TrainConfig

    with pytest.raises(ValueError, match=message):
        TrainConfig(stage="policy", data="d", out=str(tmp_path / "o"), **{field: value}).resolved().validate()


def test_every_train_config_field_names_the_flag_that_sets_it():
    """`flag_of` (used by the resume-mismatch error) against the `train` parser itself."""
    from trivla_drake.cli import build_parser
    from trivla_drake.train.config import TrainConfig, check_resume_compatible, flag_of

    parser = build_parser()
    train = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices["train"]
    dest_of = {option: action.dest for action in train._actions for option in action.option_strings}
    for field in dataclasses.fields(TrainConfig):
        flag = flag_of(field.name)
        same_name = "--" + field.name.replace("_", "-")
        if flag is None:
            assert same_name not in dest_of, field.name
        else:  # the flag exists, and is the field's (its dest is the field, or the field without a suffix / "no_")
            dest = dest_of[flag]
            assert dest in (field.name, "no_" + field.name, "no_" + field.name.removeprefix("use_")), (field.name, flag,
                                                                                                   dest)
    saved = TrainConfig(stage="policy", data="d", out="o")
    with pytest.raises(ValueError, match=r"grounding_lr_scale \(--grounding-lr-scale\) was 3.0"):
        check_resume_compatible(saved, dataclasses.replace(saved, grounding_lr_scale=0.5))


@pytest.mark.parametrize("extra, message", [
    (("--grounding-carry", "stack_blok", "--grounding-weight", "1"), r"--grounding-carry\) names unknown tasks \['stack_blok'\]"),
    (("--grounding-carry", "stack_block"), r"--grounding-carry\) adds frames to the grounding's loss: it needs"),
])
def test_grounding_carry_names_a_bad_task_or_a_missing_grounding(setup, capsys, tmp_path, extra, message):
    import re

    err = _fails_before_training(setup, capsys, tmp_path / "out", "--init", setup["good"], *extra)
    assert re.search(message, err), err


def test_a_saved_training_config_with_a_removed_option_off_loads_and_on_is_refused_naming_it():
    """Training configs saved before the experiments left list their options at the values every shipped run had:
    they load; one that turned an option on is refused, naming the field and the git tag with its code."""
    from trivla_drake.train.config import REMOVED_FIELDS, TrainConfig

    saved = {**TrainConfig(stage="policy", data="d", out="o").to_dict(), **REMOVED_FIELDS}
    assert TrainConfig.from_dict(saved) == TrainConfig(stage="policy", data="d", out="o")
    with pytest.raises(ValueError, match=r"training config\.subgoal_noise is 0\.02.*research-archive"):
        TrainConfig.from_dict({**saved, "subgoal_noise": 0.02})
    with pytest.raises(ValueError, match="unknown fields"):
        TrainConfig.from_dict({**saved, "no_such_option": 1})
