"""config_io: typed YAML configs with dotted overrides, round trips, and errors that name the field."""

# No `from __future__ import annotations`: the schemas below are read by Drake's typed YAML loader.
import argparse
import dataclasses as dc
from typing import Optional

import pytest

from trivla_drake.config_io import (
    ConfigError,
    add_config_arguments,
    config_from_args,
    dump_config,
    load_config,
    save_config,
)


@dc.dataclass
class OptimizerConfig:
    lr: float = 3e-4
    betas: list[float] = dc.field(default_factory=lambda: [0.9, 0.95])
    schedule: str = "cosine"  # an enum as a string: "cosine" or "constant"


@dc.dataclass
class TrainConfig:
    name: str = "run"
    steps: int = 100
    tasks: list[str] = dc.field(default_factory=list)
    init: Optional[str] = None
    dense: bool = False
    optimizer: OptimizerConfig = dc.field(default_factory=OptimizerConfig)
    phases: list[OptimizerConfig] = dc.field(default_factory=list)


@dc.dataclass
class JobConfig:
    train: TrainConfig = dc.field(default_factory=TrainConfig)


def write(path, text):
    path.write_text(text)
    return path


def test_round_trip_of_nested_lists_optionals_and_enum_strings(tmp_path):
    config = TrainConfig(name="s1", steps=7, tasks=["lift_red", "open_drawer"], init="ckpt/a", dense=True,
                         optimizer=OptimizerConfig(lr=1e-5, betas=[0.8, 0.9], schedule="constant"),
                         phases=[OptimizerConfig(lr=1.0), OptimizerConfig(schedule="constant")])
    save_config(config, tmp_path / "c.yaml")
    assert load_config(TrainConfig, tmp_path / "c.yaml") == config
    assert dump_config(config).splitlines()[0] == f"# {__name__}.TrainConfig"
    assert load_config(TrainConfig, write(tmp_path / "d.yaml", dump_config(TrainConfig(init=None)))) == TrainConfig()


def test_file_merges_into_defaults_field_by_field(tmp_path):
    path = write(tmp_path / "c.yaml", "steps: 5\noptimizer: {lr: 0.5}\n")
    config = load_config(TrainConfig, path, defaults=TrainConfig(name="given", optimizer=OptimizerConfig(lr=1.0,
                                                                                                         betas=[0.1])))
    assert (config.name, config.steps, config.optimizer.lr, config.optimizer.betas) == ("given", 5, 0.5, [0.1])
    assert load_config(TrainConfig, write(tmp_path / "empty.yaml", "")) == TrainConfig()


def test_overrides_apply_in_order_after_the_file(tmp_path):
    path = write(tmp_path / "c.yaml", "steps: 5\ninit: a\n")
    config = load_config(JobConfig, None, ["train.steps=6", "train.optimizer.lr=1e-4", "train.steps=8",
                                           "train.tasks=[a, b]", "train.dense=true"])
    assert (config.train.steps, config.train.optimizer.lr, config.train.tasks, config.train.dense) == \
        (8, 1e-4, ["a", "b"], True)
    config = load_config(TrainConfig, path, ["init=null", "name=2024", "steps=9"])
    assert (config.init, config.name, config.steps) == (None, "2024", 9)


def test_cli_arguments():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser)
    args = parser.parse_args(["--set", "train.steps=3", "--set", "train.name=x"])
    assert args.config is None
    config = config_from_args(JobConfig, args)
    assert (config.train.steps, config.train.name) == (3, "x")


@pytest.mark.parametrize("override, words", [
    ("train.lrr=1", ["--set train.lrr=1", "TrainConfig has no field 'lrr'"]),
    ("train.optimizer.lrr=1", ["OptimizerConfig has no field 'lrr'", "did you mean 'lr'"]),
    ("train.steps=abc", ["--set train.steps=abc", "TrainConfig.steps"]),
    ("train.steps=1.5", ["TrainConfig.steps"]),
    ("train.tasks=3", ["TrainConfig.tasks is a list"]),
    ("train.tasks=lift_red", ["TrainConfig.tasks is a list: write [lift_red]"]),
    ("train.optimizer=3", ["TrainConfig.optimizer"]),
    ("train.steps", ["--set train.steps", "dotted.field=value"]),
    ("=3", ["dotted.field=value"]),
])
def test_override_errors_name_the_override_and_field(override, words):
    with pytest.raises(ConfigError) as caught:
        load_config(JobConfig, None, [override])
    for word in words:
        assert word in str(caught.value)


@pytest.mark.parametrize("text, words", [
    ("train: {lrr: 1}\n", ["train.lrr", "TrainConfig has no field 'lrr'"]),
    ("train: {optimizer: {lr: fast}}\n", ["train.optimizer.lr", "OptimizerConfig.lr"]),
    ("train: {steps: 2, tasks: 3}\n", ["train.tasks", "TrainConfig.tasks is a list"]),
    ("train: {tasks: lift_red}\n", ["train.tasks", "TrainConfig.tasks is a list"]),
    ("train: {optimizer: 3}\n", ["train.optimizer", "TrainConfig.optimizer"]),
    ("train: {phases: [{lr: 1, bad: 2}]}\n", ["train.phases", "bad"]),
    ("- 1\n", ["must hold a mapping"]),
    ("train: [\n", ["not valid YAML"]),
])
def test_file_errors_name_the_file_and_field(tmp_path, text, words):
    path = write(tmp_path / "job.yaml", text)
    with pytest.raises(ConfigError) as caught:
        load_config(JobConfig, path)
    assert str(path) in str(caught.value)
    for word in words:
        assert word in str(caught.value)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="nope.yaml does not exist"):
        load_config(JobConfig, tmp_path / "nope.yaml")


def test_nothing_written_on_failure(tmp_path):
    @dc.dataclass
    class WithTuple:
        pair: tuple = (1, 2)

    with pytest.raises(ConfigError, match="WithTuple"):
        save_config(WithTuple(), tmp_path / "out" / "c.yaml")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    save_config(TrainConfig(), tmp_path / "c.yaml")
    before = (tmp_path / "c.yaml").read_text()
    with pytest.raises(ConfigError):
        save_config(WithTuple(), tmp_path / "c.yaml")
    assert (tmp_path / "c.yaml").read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["c.yaml"]


def test_schemas_the_loader_cannot_read_are_refused():
    @dc.dataclass(frozen=True)
    class Frozen:
        x: int = 1

    @dc.dataclass
    class Stringly:
        x: "int" = 1

    with pytest.raises(TypeError, match="frozen"):
        load_config(Frozen)
    with pytest.raises(TypeError, match="from __future__ import annotations"):
        load_config(Stringly)
