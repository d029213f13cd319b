"""Every example runs (briefly, with an untrained tiny model) and does what it says."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(script, *args, cwd=None):
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / script), "--preset", "tiny", *args],
        capture_output=True, text=True, timeout=300, env=env, cwd=cwd, stdin=subprocess.DEVNULL,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def test_closed_loop_example():
    out = _run("closed_loop.py", "--seconds", "0.6")
    assert "real-time factor" in out and "latest action chunk" in out


def test_compose_larger_diagram_example():
    out = _run("compose_larger_diagram.py", "--seconds", "0.4")
    assert "top camera: 160x120" in out and "hand target to extra block" in out


def test_meshcat_inspection_example(tmp_path):
    page = tmp_path / "run.html"
    out = _run("meshcat_inspection.py", "--seconds", "0.4", "--record", str(page))
    assert "localhost" in out and page.stat().st_size > 100_000


def test_system3_predictions_example(tmp_path):
    cv2 = pytest.importorskip("cv2")
    image = tmp_path / "fig5.png"
    _run("system3_predictions.py", "--at", "0.2", "--frame-spacing", "0.1", "--out", str(image))
    grid = cv2.imread(str(image))
    assert grid is not None and grid.shape[0] == 4 * 112  # real/predicted x static/wrist rows


def test_user_diagram_example():
    """A user's own plant (base moved and turned), cameras and driver, the policy added through the public API."""
    out = _run("user_diagram.py", "--seconds", "0.4")
    assert "hand (world)" in out and "tracking error" in out
