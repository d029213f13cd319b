"""Training checkpoints: a model checkpoint (`trivla_drake.nn.save_checkpoint`: model.safetensors +
config.json, loadable by `load_checkpoint`) plus training_state.pt (optimizer, step, every rank's RNG
states) and train_config.yaml (the full `TrainConfig`; a checkpoint of before the nested config has a flat
train_config.json instead, which still reads).

Atomicity: a checkpoint is written into a hidden temporary folder next to its final place, its files
are flushed to disk, and the folder is renamed into place. A folder named `step-XXXXXXXX` is therefore
always complete; a killed run leaves at most a `.tmp-*` folder, which is ignored and cleaned up.

    OUT/checkpoints/step-00000500/   periodic (the newest `keep_checkpoints` are kept)
    OUT/final/                       the last step's checkpoint
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any

import torch
import yaml

from trivla_drake.config_io import save_config
from trivla_drake.nn.checkpoint import save_checkpoint
from trivla_drake.train.atomic_folder import atomic_folder
from trivla_drake.train.config import TrainConfig

CHECKPOINTS_DIR = "checkpoints"
FINAL_DIR = "final"
STATE_FILE = "training_state.pt"
TRAIN_CONFIG_FILE = "train_config.yaml"
FLAT_TRAIN_CONFIG_FILE = "train_config.json"  # checkpoints written before the nested TrainConfig
STEP_FILE = "step.json"  # {"step": N}: read without loading the optimizer state
_STEP_DIR = re.compile(r"^step-(\d{8})$")


def step_dir_name(step: int) -> str:
    """Folder name of the periodic checkpoint of `step`."""
    return f"step-{step:08d}"


def write_folder_atomically(target: str | os.PathLike, fill) -> Path:
    """Calls fill(tmp) on a fresh, empty temporary folder next to `target`, then puts it in place as `target`
    (`atomic_folder`: flushed to disk, renamed); the temporary folder is removed if `fill` fails, and an existing
    `target` stays intact."""
    with atomic_folder(target) as tmp:
        fill(tmp)
    return Path(target)


def write_checkpoint(
    target: str | os.PathLike,
    *,
    model: torch.nn.Module,
    train_state: dict[str, Any],
    config: TrainConfig,
) -> Path:
    """Writes a complete training checkpoint to `target` atomically; returns its path."""

    def fill(tmp: Path) -> None:
        save_checkpoint(model, str(tmp))
        torch.save(train_state, tmp / STATE_FILE)
        (tmp / STEP_FILE).write_text(json.dumps({"step": int(train_state["step"])}))
        save_config(config, tmp / TRAIN_CONFIG_FILE)

    return write_folder_atomically(target, fill)


def copy_checkpoint(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Copies a complete checkpoint folder to `target` atomically."""
    return write_folder_atomically(target, lambda tmp: shutil.copytree(source, tmp, dirs_exist_ok=True))


def export_checkpoint(
    source: str | os.PathLike,
    target: str | os.PathLike,
    *,
    weights_dtype: str = "float16",
    drop_unused_llm_layers: bool = False,
    job_config: tuple[str, Any] | None = None,
) -> Path:
    """Writes the model of checkpoint `source` (no optimizer state) to `target` atomically, its weights in
    `weights_dtype` (float16: half the size, e.g. the shipped models/trivla_cpu). With
    `drop_unused_llm_layers`, System 2's LLM keeps only the layers up to its read-out layer: the same
    Q_vl and actions, a smaller file, but no longer a start for the vlm stage. An existing `target`
    is replaced only once the new one is complete. `job_config` (file name, config): the job's config, written into
    the folder as YAML beside the model."""
    from trivla_drake.nn.checkpoint import load_checkpoint

    model = load_checkpoint(str(source))
    if drop_unused_llm_layers and model.vision_language is not None:
        model.vision_language.drop_layers_above_readout()
    return write_model_folder(target, model, weights_dtype=weights_dtype, job_config=job_config)


def write_model_folder(target: str | os.PathLike, model: torch.nn.Module, *, weights_dtype: str,
                       job_config: tuple[str, Any] | None = None) -> Path:
    """Writes `model` (config.json + weights in `weights_dtype`) and, if given, `job_config` (file name, the config
    of the job that made it, as YAML) to the folder `target`, atomically."""

    def fill(tmp: Path) -> None:
        save_checkpoint(model, str(tmp), weights_dtype=weights_dtype)
        if job_config is not None:
            save_config(job_config[1], tmp / job_config[0])

    return write_folder_atomically(target, fill)


def list_checkpoints(out: str | os.PathLike) -> list[tuple[int, Path]]:
    """(step, folder) of every complete periodic checkpoint in `out`, oldest first."""
    root = Path(out) / CHECKPOINTS_DIR
    if not root.is_dir():
        return []
    found = []
    for path in root.iterdir():
        match = _STEP_DIR.match(path.name)
        if match and path.is_dir():
            found.append((int(match.group(1)), path))
    return sorted(found)


def latest_checkpoint(out: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint of a run (periodic or final), or None."""
    candidates = [(step, path) for step, path in list_checkpoints(out)]
    final = Path(out) / FINAL_DIR
    if (final / STEP_FILE).is_file():
        candidates.append((read_step(final), final))
    if not candidates:
        return None
    return max(candidates, key=lambda c: (c[0], c[1].name == FINAL_DIR))[1]


def checkpoint_problem(directory: str | os.PathLike) -> str | None:
    """Why checkpoint `directory` cannot be resumed from (a truncated or corrupt file, named), or None when its
    training state, training config, model config and weights all read."""
    from safetensors import safe_open

    from trivla_drake.nn.checkpoint import CONFIG_FILE, WEIGHTS_FILE, read_checkpoint_config

    try:
        read_step(directory)
        load_train_state(directory)
        load_train_config(directory)
        read_checkpoint_config(str(directory))
        weights = Path(directory) / WEIGHTS_FILE
        try:
            with safe_open(str(weights), framework="pt", device="cpu") as f:
                for key in f.keys():
                    f.get_tensor(key)
        except Exception as exc:  # noqa: BLE001 - safetensors raises its own types for truncated files
            raise ValueError(f"{weights} is missing, truncated or corrupt: {exc}") from exc
    except (OSError, ValueError) as exc:
        return str(exc).splitlines()[0] if str(exc) else f"{CONFIG_FILE}: {type(exc).__name__}"
    return None


def newest_intact_checkpoint(out: str | os.PathLike, *, set_aside: bool) -> tuple[Path | None, list[tuple[Path, str, Path]]]:
    """The newest checkpoint of run `out` that can be resumed from (`checkpoint_problem`), and the newer ones
    skipped: (folder, why, where it is kept). With `set_aside` (one process only) and an intact checkpoint found, a
    skipped folder is renamed to `<name>.unreadable` beside it, never deleted: the resumed run would otherwise
    replace it when it reaches its step, and `prune_checkpoints` would delete it."""
    candidates = [path for _, path in list_checkpoints(out)]
    final = Path(out) / FINAL_DIR
    if final.is_dir():
        candidates.append(final)

    def order(path: Path) -> tuple[int, bool]:
        try:
            return read_step(path), path.name == FINAL_DIR
        except ValueError:
            return -1, path.name == FINAL_DIR

    skipped: list[tuple[Path, str]] = []
    for path in sorted(candidates, key=order, reverse=True):
        problem = checkpoint_problem(path)
        if problem is None:
            kept = [(broken, why, _set_aside(broken) if set_aside else broken) for broken, why in skipped]
            return path, kept
        skipped.append((path, problem))
    return None, [(broken, why, broken) for broken, why in skipped]


def _set_aside(folder: Path) -> Path:
    target = folder.with_name(f"{folder.name}.unreadable")
    n = 1
    while target.exists():
        n += 1
        target = folder.with_name(f"{folder.name}.unreadable-{n}")
    os.rename(folder, target)
    return target


def read_step(directory: str | os.PathLike) -> int:
    """The step a checkpoint was written at."""
    path = Path(directory) / STEP_FILE
    try:
        return int(json.loads(path.read_text())["step"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} is missing or unreadable: {exc}") from exc


def prune_checkpoints(out: str | os.PathLike, keep: int) -> None:
    """Deletes all but the newest `keep` periodic checkpoints and leftover temporary folders."""
    found = list_checkpoints(out)
    for _, path in found[: max(0, len(found) - keep)]:
        shutil.rmtree(path, ignore_errors=True)
    root = Path(out) / CHECKPOINTS_DIR
    if root.is_dir():
        for path in root.iterdir():
            if path.name.startswith((".tmp-", ".old-")) and f"-{os.getpid()}-" not in path.name:
                shutil.rmtree(path, ignore_errors=True)


def load_train_state(directory: str | os.PathLike) -> dict[str, Any]:
    """training_state.pt of a checkpoint; ValueError when missing, truncated or corrupt."""
    path = Path(directory) / STATE_FILE
    if not path.is_file():
        raise ValueError(f"{directory} is not a training checkpoint: {STATE_FILE} is missing")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises various errors for truncated or corrupt files
        raise ValueError(f"{path} is truncated or corrupt: {exc}") from exc
    if not isinstance(state, dict) or "step" not in state:
        raise ValueError(f"{path} is not a training state (no 'step')")
    return state


def load_train_config(directory: str | os.PathLike) -> TrainConfig:
    """The training config a checkpoint (or a run folder) holds: train_config.yaml, else the flat train_config.json
    of a checkpoint written before the nested config."""
    path = Path(directory) / TRAIN_CONFIG_FILE
    if not path.is_file() and (Path(directory) / FLAT_TRAIN_CONFIG_FILE).is_file():
        path = Path(directory) / FLAT_TRAIN_CONFIG_FILE
    if not path.is_file():
        raise ValueError(f"{directory} is not a training checkpoint: {TRAIN_CONFIG_FILE} is missing")
    try:
        data = yaml.safe_load(path.read_text())  # JSON is YAML
        return TrainConfig.from_dict(data if data is not None else {})
    except (ValueError, TypeError, yaml.YAMLError) as exc:
        raise ValueError(f"{path} is unreadable: {exc}") from exc
