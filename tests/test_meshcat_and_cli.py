"""Meshcat stays on localhost, a recorded run saves as one HTML page that Chromium loads, and the CLI."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time

import pytest


def test_meshcat_listens_on_localhost_only():
    from trivla_drake.station.meshcat_setup import make_meshcat

    meshcat = make_meshcat()
    assert meshcat.web_url().startswith("http://localhost:")


def _chromium_driver():
    webdriver = pytest.importorskip("selenium.webdriver")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    chromedriver = shutil.which("chromedriver")
    if not (chromium and chromedriver):
        pytest.skip("Debian's chromium and chromium-driver are not installed")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(chromedriver), options=options)


def test_recorded_run_opens_in_headless_chromium(tmp_path):
    out = tmp_path / "run.html"
    result = subprocess.run(
        [sys.executable, "-m", "trivla_drake.cli", "sim", "--seconds", "0.5", "--record", str(out), "--json"],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert out.stat().st_size > 100_000  # meshes and animation are inside the page
    driver = _chromium_driver()
    try:
        driver.get(out.as_uri())
        names = []
        for _ in range(60):
            names = driver.execute_script(
                "if (typeof viewer === 'undefined') return [];"
                "const names = []; viewer.scene.traverse(o => names.push(o.name)); return names;"
            )
            if any("panda" in n for n in names):
                break
            time.sleep(0.5)
    finally:
        driver.quit()
    for expected in ("panda", "block_red", "drawer", "button"):
        assert any(expected in n for n in names), f"{expected} is not in the page's scene"


def test_sim_json_reports_timing():
    result = subprocess.run(
        [sys.executable, "-m", "trivla_drake.cli", "sim", "--seconds", "0.3", "--json"],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["sim_time"] == pytest.approx(0.3)
    assert report["wall_time"] > 0 and report["realtime_factor"] > 0


def test_cli_bad_scenario_exits_with_a_clear_message(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "trivla_drake.cli", "sim", "--set", f"scenario={tmp_path / 'missing.yaml'}"],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 2
    assert "missing.yaml" in result.stderr and "Traceback" not in result.stderr
