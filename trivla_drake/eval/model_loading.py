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


def load_model(checkpoint: str | Path | None = None, *, preset: str = "cpu", seed: int = 0) -> TriVLA:
    """The checkpoint at `checkpoint`; else the shipped default checkpoint; else an UNTRAINED model
    of `preset` (logged as a warning: its actions are random, useful for timing and wiring only)."""
    if checkpoint is not None:
        return load_checkpoint(str(checkpoint)).eval()
    default = default_checkpoint_dir()
    if (default / "config.json").exists():
        return load_checkpoint(str(default)).eval()
    _log.warning("no TriVLA checkpoint given and none at %s: using an UNTRAINED '%s' model", default, preset)
    return TriVLA(make_config(preset, init_seed=seed), load_pretrained=False).eval()
