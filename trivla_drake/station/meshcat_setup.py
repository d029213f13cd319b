"""Meshcat on localhost only, and saving a recorded run as one self-contained HTML page."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from pydrake.geometry import Meshcat, MeshcatParams


def make_meshcat(port: int | None = None) -> Meshcat:
    """A Meshcat server listening on localhost only (Drake's default is every interface)."""
    params = MeshcatParams(host="localhost")
    if port is not None:
        params.port = port
    meshcat = Meshcat(params)
    # Start looking at the table from the front-left, not from Meshcat's far default.
    meshcat.SetCameraPose(camera_in_world=[1.5, 1.0, 0.9], target_in_world=[0.4, 0.0, 0.1])
    return meshcat


def save_static_html(meshcat: Meshcat, path: str | os.PathLike) -> Path:
    """Write Meshcat's current scene (and published recording) to `path`, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    html = meshcat.StaticHtml()
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as stream:
            stream.write(html)
        os.chmod(tmp, 0o644)  # mkstemp's 0600 would hide the page from a web server
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
