"""Content checksums of a dataset's data and video files: meta/checksums.json maps each file's path (relative to
the dataset folder) to the sha256 of its bytes, recorded when the file is written (`LeRobotWriter`) and checked
when the dataset is read for training or feature caching (`LeRobotReader.episode_digests`). A separate meta file,
so the folder stays the LeRobot v3 layout that LeRobot itself reads.

A dataset written before checksums were recorded has no meta/checksums.json: it is read with a one-line warning
(its files cannot be checked), and `python -m trivla_drake.data.checksums DATASET` records its files as they are
now (also the way to accept a file replaced on purpose).
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path

from trivla_drake.data.durable import atomic_write_bytes

CHECKSUMS_PATH = "meta/checksums.json"
ALGORITHM = "sha256"
RECORD_COMMAND = "python -m trivla_drake.data.checksums"


class DatasetCorruptError(ValueError):
    """A dataset file whose content is not what was written (or that is gone)."""


def file_sha256(path: str | os.PathLike) -> str:
    """The sha256 hex digest of the bytes of the file at `path`."""
    hasher = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            hasher.update(block)
    return hasher.hexdigest()


def read_checksums(root: str | os.PathLike) -> dict[str, str] | None:
    """The recorded checksums (relative path -> sha256) of the dataset at `root`; None when it records none."""
    path = Path(root) / CHECKSUMS_PATH
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        files = data["files"]
        if data.get("algorithm") != ALGORITHM or not isinstance(files, dict):
            raise ValueError(f"algorithm must be {ALGORITHM!r} and files an object")
    except (ValueError, KeyError, TypeError) as error:
        raise DatasetCorruptError(f"{path} is unreadable ({type(error).__name__}: {error}): record the checksums "
                                  f"again with `{RECORD_COMMAND} {root}` once the files are known to be good") from error
    return {str(k): str(v) for k, v in files.items()}


def write_checksums(root: str | os.PathLike, checksums: dict[str, str]) -> None:
    """Writes meta/checksums.json atomically (the old record or the new one, never a part)."""
    data = {"algorithm": ALGORITHM, "files": dict(sorted(checksums.items()))}
    atomic_write_bytes(Path(root) / CHECKSUMS_PATH, json.dumps(data, indent=1).encode())


def check_file(root: str | os.PathLike, relative: str, recorded: dict[str, str]) -> str:
    """The sha256 of dataset file `relative`; DatasetCorruptError naming it when it is missing, unrecorded, or
    differs from its recorded checksum."""
    path = Path(root) / relative
    fix = (f"restore it from a copy of the dataset or collect the dataset again; if it was replaced on purpose, "
           f"record the files as they are now with `{RECORD_COMMAND} {root}`")
    if not path.is_file():
        raise DatasetCorruptError(f"dataset file {path} is missing: {fix}")
    if relative not in recorded:
        raise DatasetCorruptError(f"dataset file {path} has no checksum in {Path(root) / CHECKSUMS_PATH}: {fix}")
    digest = file_sha256(path)
    if digest != recorded[relative]:
        raise DatasetCorruptError(f"dataset file {path} is corrupted or was changed since it was written "
                                  f"({ALGORITHM} {digest[:12]}..., recorded {recorded[relative][:12]}...): {fix}")
    return digest


def main(argv: list[str] | None = None) -> int:
    """Records the checksums of every committed episode's files of the datasets named on the command line."""
    from trivla_drake.data.lerobot_reader import LeRobotReader

    folders = sys.argv[1:] if argv is None else argv
    if not folders:
        print(f"usage: {RECORD_COMMAND} DATASET [DATASET ...]", file=sys.stderr)
        return 2
    for folder in folders:
        reader = LeRobotReader(folder)
        files = [f for e in range(reader.num_episodes) for f in reader.episode_files(e)]
        write_checksums(folder, {f: file_sha256(Path(folder) / f) for f in files})
        print(f"{Path(folder) / CHECKSUMS_PATH}: {len(files)} files of {reader.num_episodes} episodes recorded")
    return 0


if __name__ == "__main__":
    sys.exit(main())
