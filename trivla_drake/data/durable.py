"""Files written durably: `fsync_file` puts a file's bytes on disk before it is renamed into place (so a power
loss after the rename cannot leave an empty or partial file under the final name); `atomic_write_text`."""

from __future__ import annotations

import os


def fsync_file(path: str | os.PathLike) -> None:
    """Flushes the file at `path` (already closed by its writer) to disk."""
    with open(path, "rb") as stream:
        os.fsync(stream.fileno())


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Writes `text` to `path` through a flushed temporary sibling and a rename: a crash leaves the old
    file or the new one, never a part."""
    from pathlib import Path

    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w") as stream:
        stream.write(text)
        stream.flush()
        os.fsync(stream.fileno())
    os.replace(tmp, path)
