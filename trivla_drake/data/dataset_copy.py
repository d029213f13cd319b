"""A copy of a dataset folder, the start of a larger one: the shipped recipe extends copies of its datasets (the
clean demonstrations plus DART recoveries, the prelude demonstrations plus more), so each stays what it was when
the models that read it were trained. The copy is written atomically; an existing destination is never touched."""

# No `from __future__ import annotations` here: DatasetCopyConfig is read by Drake's typed YAML loader.
import dataclasses as dc
import shutil
from pathlib import Path

from trivla_drake.data.lerobot_reader import LeRobotReader


@dc.dataclass
class DatasetCopyConfig:
    """Which dataset to copy where."""

    # The dataset folder to copy (written by `collect`).
    source: str = ""
    # The new folder (must not exist yet: an existing one is the earlier copy, perhaps extended since, and is kept).
    dest: str = ""


def copy_dataset(config: DatasetCopyConfig) -> None:
    """Copies `config.source` to `config.dest` atomically; ValueError naming the field when the source is not a dataset
    or the destination exists."""
    from trivla_drake.train.atomic_folder import atomic_folder

    if not config.source or not config.dest:
        raise ValueError("DatasetCopyConfig.source and .dest are both needed")
    LeRobotReader(config.source)  # a clear error unless the source is a dataset
    if Path(config.dest).exists():
        raise ValueError(f"DatasetCopyConfig.dest {config.dest} exists already: it is kept as it is (remove it to copy "
                         "again)")
    with atomic_folder(config.dest) as tmp:
        shutil.copytree(config.source, tmp, dirs_exist_ok=True)


def dataset_copy_done(config: DatasetCopyConfig) -> bool:
    """Whether the copy exists (later stages may have extended it since)."""
    return (Path(config.dest) / "meta" / "info.json").is_file()


def describe_dataset_copy(config: DatasetCopyConfig) -> str:
    """The shell command that does the same."""
    return f"cp -r {config.source} {config.dest}"
