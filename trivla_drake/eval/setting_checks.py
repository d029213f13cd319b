"""Checks of the settings the rollout commands share (a time, a Meshcat port, a recording's file, an instruction),
each a ValueError naming the flag or config field it is given, raised before anything runs."""

from __future__ import annotations

import math
from pathlib import Path

# Ports a Meshcat server can listen on (0: any free port).
PORTS = range(0, 65536)


def check_seconds(seconds: float | None, flag: str) -> float | None:
    """`seconds` if None (the default) or a finite time above 0; else ValueError naming `flag` (nan, inf and -1 would
    run forever or stop at once)."""
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{flag} must be a finite number of seconds above 0, got {seconds}")
    return seconds


def check_port(port: int | None, flag: str = "port") -> int | None:
    """`port` if None (Drake's default, 7000 up) or 0 to 65535 (0: any free port); else ValueError naming `flag`."""
    if port is not None and port not in PORTS:
        raise ValueError(f"{flag} must be a port from {PORTS.start} to {PORTS.stop - 1} (0: any free port), got {port}")
    return port


def check_record_path(path: str | None, flag: str = "--record") -> str | None:
    """`path` if None or where a recording's HTML file can be written; else ValueError naming `flag` (checked before
    a simulation runs, not when its recording is saved)."""
    if path is None:
        return None
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{flag} {path} is a folder: give a file name, e.g. {target / 'run.html'}")
    blocking = next((parent for parent in target.parents if parent.exists()), None)
    if blocking is not None and not blocking.is_dir():
        raise ValueError(f"{flag} {path}: {blocking} is a file, not a folder")
    return path


def check_instruction_text(text: str | None, flag: str = "--instruction") -> str | None:
    """`text` if None (the task's own) or a non-empty instruction that is valid text (a command-line argument in
    another encoding than UTF-8 arrives with its bad bytes as surrogates); else ValueError naming `flag`."""
    if text is None:
        return None
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as error:
        bad = text[error.start:error.end].encode("utf-8", "backslashreplace").decode("ascii")
        raise ValueError(f"{flag} is not UTF-8 text ({bad} at character {error.start}: a byte that is not UTF-8); "
                         "give the instruction in UTF-8") from None
    if not text.strip():
        raise ValueError(f"{flag} is empty; give the task in words, e.g. 'pick up the red block' (or leave it out "
                         "for the task's own instruction)")
    return text
