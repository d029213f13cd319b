"""A folder written atomically and durably: filled under a temporary name, its files flushed to disk, renamed into
place only when complete (a folder under its final name is always whole, even after a power loss); a cached folder
keyed by its settings (its meta.json), made once that way and never overwritten by other settings; and the check that
an output folder may be replaced at all (never the working folder, nor a user's folder of other things)."""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from trivla_drake.data.durable import fsync_directory, fsync_file


@contextmanager
def atomic_folder(folder: str | os.PathLike) -> Iterator[Path]:
    """Yields a new, empty temporary sibling of `folder` to fill. When the block ends without an error its files are
    flushed to disk and it replaces `folder`; on an error it is removed and `folder` is left as it was."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.with_name(f".tmp-{folder.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    tmp.mkdir()
    try:
        yield tmp
        _fsync_tree(tmp)
        replace_folder(tmp, folder)
        fsync_directory(folder.parent)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def replace_folder(new: Path, target: Path) -> None:
    """Renames the complete folder `new` to `target`. An older `target` is set aside, not deleted, until `new` is in
    place, so a crash in between loses neither (the set-aside copy keeps its contents under `.old-*`)."""
    if not target.exists():
        os.rename(new, target)
        return
    old = target.with_name(f".old-{target.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    os.rename(target, old)
    os.rename(new, target)
    shutil.rmtree(old, ignore_errors=True)


def check_replaceable_folder(folder: str | os.PathLike, *, flag: str, holds_earlier_output: Callable[[Path], bool],
                             what: str, overwrite: bool = False, overwrite_flag: str = "--overwrite") -> None:
    """ValueError naming `flag` unless `folder` may be replaced by a new folder of `what`: it does not exist, is empty,
    or holds an earlier `what` (`holds_earlier_output(folder)`), or `overwrite` is given. Never (not even with
    `overwrite`) a file, the working folder or a folder holding it: replacing those would delete the user's files."""
    folder = Path(folder)
    if not folder.exists() and not folder.is_symlink():
        return
    if not folder.is_dir():
        raise ValueError(f"{flag} {folder} is a file, not a folder: choose a folder for the {what}")
    resolved, cwd = folder.resolve(), Path.cwd().resolve()
    if resolved == cwd or resolved in cwd.parents:
        raise ValueError(f"{flag} {folder} is the working folder {cwd} or holds it: replacing it would delete "
                         f"everything in it; choose a new folder for the {what}")
    entries = sorted(p.name for p in folder.iterdir())
    if not entries or holds_earlier_output(folder) or overwrite:
        return
    shown = ", ".join(entries[:3]) + (f" and {len(entries) - 3} more" if len(entries) > 3 else "")
    raise ValueError(f"{flag} {folder} is not empty ({shown}) and does not hold an earlier {what}: choose a new "
                     f"folder, or pass {overwrite_flag} to replace it and delete everything in it")


def _fsync_tree(directory: Path) -> None:
    """Flushes every file under `directory` and every folder's names, `directory`'s own included."""
    for path in directory.rglob("*"):
        if path.is_symlink():
            continue
        (fsync_directory if path.is_dir() else fsync_file)(path)
    fsync_directory(directory)


def ensure_cached_folder(folder: str | os.PathLike, settings: dict[str, Any], make: Callable[[], Path], *,
                         what: str) -> Path:
    """`folder` as it is when its meta.json holds `settings`; `make()` (which writes it, with that meta.json) when the
    folder is absent or empty. ValueError, naming `what` the folder should hold, when it holds something else, an
    unreadable meta.json, or a set made with other settings (it is never overwritten)."""
    folder = Path(folder)
    meta_path = folder / "meta.json"
    if not meta_path.is_file():
        if folder.exists() and any(folder.iterdir()):
            raise ValueError(f"{folder} is not empty and does not hold {what} (no meta.json): choose another folder")
        return make()
    try:
        meta = json.loads(meta_path.read_text())
    except ValueError as exc:
        raise ValueError(f"{meta_path} is not valid JSON ({exc}): delete {folder} to make the {what} again") from exc
    differing = {k: (meta.get(k), v) for k, v in settings.items() if meta.get(k) != v}
    if differing:
        detail = ", ".join(f"{k}: {old!r} there, {new!r} asked" for k, (old, new) in differing.items())
        raise ValueError(f"{folder} holds {what} made with other settings ({detail}); use another folder")
    return folder
