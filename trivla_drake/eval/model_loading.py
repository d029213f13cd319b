"""Which TriVLA model a run uses: a checkpoint, the shipped default, or an untrained preset."""

from __future__ import annotations

import logging
from pathlib import Path

from trivla_drake.nn import TriVLA, load_checkpoint, make_config
from trivla_drake.station.scenario import models_dir

_log = logging.getLogger(__name__)
DEFAULT_CHECKPOINT_NAME = "trivla_cpu"


def default_checkpoint_dir() -> Path:
    """Where the project's trained `cpu` checkpoint lives: models/trivla_cpu/."""
    return models_dir() / DEFAULT_CHECKPOINT_NAME


def check_model_choice(checkpoint, preset) -> None:
    """ValueError when both a checkpoint and a preset are given (one says which model to load)."""
    if checkpoint is not None and preset is not None:
        raise ValueError("--preset (an UNTRAINED model of that preset) and --checkpoint (a trained one): give one")


def load_model(checkpoint: str | Path | None = None, *, preset: str | None = None, seed: int = 0) -> TriVLA:
    """The checkpoint at `checkpoint`; else, when `preset` is given, an UNTRAINED model of that preset
    (for wiring and timing; logged as a warning: its actions are meaningless); else the shipped default
    checkpoint (models/trivla_cpu), FileNotFoundError when it is missing."""
    check_model_choice(checkpoint, preset)
    if checkpoint is not None:
        return load_checkpoint(str(checkpoint)).eval()
    if preset is not None:
        _log.warning("no TriVLA checkpoint given: using an UNTRAINED '%s' model (--preset)", preset)
        return TriVLA(make_config(preset, init_seed=seed), load_pretrained=False).eval()
    default = default_checkpoint_dir()
    if not (default / "config.json").is_file():
        raise FileNotFoundError(
            f"the shipped default checkpoint is missing: no config.json in {default} (restore it, e.g. "
            f"`git checkout -- models/{DEFAULT_CHECKPOINT_NAME}`); or give --checkpoint DIR, or --preset NAME for "
            "an UNTRAINED model")
    return load_checkpoint(str(default)).eval()
