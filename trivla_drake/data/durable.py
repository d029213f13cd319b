"""Files written durably: `fsync_file` (and `fsync_directory`, for a folder's names) puts a file's bytes on disk before it is renamed into place (so a power
loss after the rename cannot leave an empty or partial file under the final name); `atomic_write_bytes` and
`atomic_write_text` write through such a flushed temporary sibling."""

from __future__ import annotations

import os
from pathlib import Path


def fsync_file(path: str | os.PathLike) -> None:
    """Flushes the file at `path` (already closed by its writer) to disk."""
    with open(path, "rb") as stream:
        os.fsync(stream.fileno())


def fsync_directory(path: str | os.PathLike) -> None:
    """Flushes a folder's entries (the names of the files in it) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Writes `data` to `path` (its folder made if missing) through a flushed temporary sibling and a rename: a
    crash leaves the old file or the new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as stream:
        stream.write(data)
        stream.flush()
        os.fsync(stream.fileno())
    os.replace(tmp, path)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """`atomic_write_bytes` of `text` in UTF-8."""
    atomic_write_bytes(path, text.encode())
