"""The training jobs as recipe stage kinds (trivla_drake/recipe.py): "train", "export", "soup" and "refit", each with
its config dataclass as schema, a `run` that resumes a killed train run, an `is_done` that holds once the output is
complete, and a `describe` that prints the equivalent `trivla-drake ...` command line. Registered on import."""

from __future__ import annotations

import dataclasses
import json
import shlex
from pathlib import Path
from typing import Any

from trivla_drake.recipe import register_stage_kind
from trivla_drake.train.config import TrainConfig, differing_fields
from trivla_drake.train.export_job import (
    EXPORT_CONFIG_FILE,
    REFIT_CONFIG_FILE,
    SOUP_CONFIG_FILE,
    ExportConfig,
    SoupConfig,
    holds_export_of,
)
from trivla_drake.train.refit_job import RefitConfig

# TrainConfig's fields that `train` has a flag for (the rest go in --set).
TRAIN_FLAGS = ("stage", "data", "out", "init", "preset", "steps", "seed", "threads")


def run_train_stage(config: TrainConfig, workdir: str) -> None:
    """Trains `config`'s run, resuming it where a killed run left checkpoints in its out folder."""
    from trivla_drake.train import checkpoints as ckpt
    from trivla_drake.train.trainer import train

    train(dataclasses.replace(config, resume=config.resume or ckpt.latest_checkpoint(config.out) is not None))


def train_stage_done(config: TrainConfig, workdir: str) -> bool:
    """Whether OUT/final holds an intact checkpoint of the run's last step."""
    from trivla_drake.train import checkpoints as ckpt

    final = Path(config.out) / ckpt.FINAL_DIR
    if not final.is_dir() or ckpt.checkpoint_problem(final) is not None:
        return False
    steps = config.steps if config.steps is not None else config.resolved().steps
    return ckpt.read_step(final) == steps


def describe_train(config: TrainConfig) -> str:
    """The `trivla-drake train` command line that runs `config`."""
    words = ["trivla-drake", "train"]
    for name in TRAIN_FLAGS:
        value = getattr(config, name)
        if value is not None and (name in ("stage", "out") or value != getattr(TrainConfig(), name)):
            words += [f"--{name}", str(value)]
    words += ["--resume"] * config.resume + ["--no-progress"] * (not config.progress)
    return _joined(words, config, TrainConfig(), skip={*TRAIN_FLAGS, "resume", "progress"})


def describe_job(command: str, positional: list[str], flags: dict[str, Any], config, skip: set[str]) -> str:
    """The `trivla-drake COMMAND` line of an export/soup/refit config: positional arguments, --out, the given
    flags, --set for the other fields that differ from their defaults."""
    words = ["trivla-drake", command, *positional, "--out", config.out]
    for flag, value in flags.items():
        if value:
            words += [flag] if value is True else [flag, str(value)]
    words += ["--overwrite"] * config.overwrite
    return _joined(words, config, type(config)(), skip={*skip, "out", "overwrite"})


def _joined(words: list[str], config, defaults, *, skip: set[str]) -> str:
    for dotted, value, _ in differing_fields(config, defaults):
        if dotted not in skip:
            text = value if isinstance(value, str) else json.dumps(value)  # JSON is YAML, as --set reads it
            words += ["--set", f"{dotted}={text}"]
    return " ".join(shlex.quote(word) for word in words)


def _run_export(config: ExportConfig, workdir: str) -> None:
    from trivla_drake.train.export_job import run_export

    run_export(config)


def _run_soup(config: SoupConfig, workdir: str) -> None:
    from trivla_drake.train.export_job import run_soup

    run_soup(config)


def _run_refit(config: RefitConfig, workdir: str) -> None:
    from trivla_drake.train.refit_job import run_refit

    run_refit(config, progress=False)


register_stage_kind("train", TrainConfig, run=run_train_stage, is_done=train_stage_done, describe=describe_train)
register_stage_kind("export", ExportConfig, run=_run_export,
                    is_done=lambda config, workdir: holds_export_of(config.out, config, EXPORT_CONFIG_FILE),
                    describe=lambda config: describe_job("export", [config.checkpoint], {}, config, {"checkpoint"}))
register_stage_kind("soup", SoupConfig, run=_run_soup,
                    is_done=lambda config, workdir: holds_export_of(config.out, config, SOUP_CONFIG_FILE),
                    describe=lambda config: describe_job("soup", list(config.checkpoints), {}, config, {"checkpoints"}))
register_stage_kind("refit", RefitConfig, run=_run_refit,
                    is_done=lambda config, workdir: holds_export_of(config.out, config, REFIT_CONFIG_FILE),
                    describe=lambda config: describe_job("refit", [config.checkpoint], {"--data": config.data},
                                                         config, {"checkpoint", "data"}))
