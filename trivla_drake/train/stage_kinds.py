"""The training jobs as recipe stage kinds (trivla_drake/recipe.py): "train", "export", "soup" and "refit", each with
its config dataclass as schema, a `run` that resumes a killed train run, an `is_done` that holds once the output is
complete, and a `describe` that prints the equivalent `trivla-drake ...` command line. Registered on import."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from trivla_drake.config_io import describe_command
from trivla_drake.recipe import register_stage_kind
from trivla_drake.train.cli_commands import JOB_FLAGS, TRAIN_FLAGS
from trivla_drake.train.config import TrainConfig, check_resume_compatible
from trivla_drake.train.export_job import (
    EXPORT_CONFIG_FILE,
    REFIT_CONFIG_FILE,
    SOUP_CONFIG_FILE,
    ExportConfig,
    SoupConfig,
    holds_export_of,
)
from trivla_drake.train.refit_job import RefitConfig

def run_train_stage(config: TrainConfig, workdir: str) -> None:
    """Trains `config`'s run, resuming it where a killed run left checkpoints in its out folder."""
    from trivla_drake.train import checkpoints as ckpt
    from trivla_drake.train.trainer import train

    train(dataclasses.replace(config, resume=config.resume or ckpt.latest_checkpoint(config.out) is not None))


def train_stage_done(config: TrainConfig, workdir: str) -> bool:
    """Whether OUT/final (written whole or not at all) is the last step of a run that `config` may resume: its step is
    the config's steps and its train_config.yaml differs from `config` only where a resumed run may differ. Reads
    two small files: no weights, no optimizer state."""
    from trivla_drake.nn.checkpoint import CONFIG_FILE, WEIGHTS_FILE
    from trivla_drake.train import checkpoints as ckpt

    final = Path(config.out) / ckpt.FINAL_DIR
    if not all((final / name).is_file() for name in (CONFIG_FILE, WEIGHTS_FILE, ckpt.STATE_FILE)):
        return False
    try:
        saved = ckpt.load_train_config(final)
        current = config.resolved()
        if current.preset is None:  # as the trainer resumes: the run's preset
            current = dataclasses.replace(current, preset=saved.preset)
        check_resume_compatible(saved, current)
        return ckpt.read_step(final) == current.steps
    except ValueError:
        return False


def describe_train(config: TrainConfig) -> str:
    """The `trivla-drake train` command line that runs `config`."""
    return describe_command("train", config, TRAIN_FLAGS, always=("stage", "out"))


def describe_job(command: str, positional: list[str], flags: dict[str, str], config, skip: set[str]) -> str:
    """The `trivla-drake COMMAND` line of an export/soup/refit config: positional arguments (the fields `skip`),
    --out, the `flags` (field -> flag) and --overwrite where set, --set for the other fields that differ from their
    defaults."""
    return describe_command(command, config, {**flags, **JOB_FLAGS}, leading=positional, skip=skip, always=("out",))


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
                    describe=lambda config: describe_job("refit", [config.checkpoint], {"data": "--data"},
                                                         config, {"checkpoint"}))
