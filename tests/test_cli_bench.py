"""`trivla-drake bench` prints one JSON object with the figures the issues ask for."""

from __future__ import annotations

import json
import subprocess
import sys


def _bench(*args):
    result = subprocess.run(
        [sys.executable, "-m", "trivla_drake.cli", "bench", "--json", *args],
        capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_station_bench_reports_diffik_and_realtime_factors():
    report = _bench("--set", "seconds=0.6", "--set", "diffik_problems=50", "--preset", "tiny")
    for key in ("diffik_median_us", "drake_diffik_median_us", "station_rtf_cameras", "station_rtf_no_cameras",
                "closed_loop_rtf"):
        assert report[key] > 0, key
    # Rendering two cameras costs time: the run without them is faster.
    assert report["station_rtf_no_cameras"] > report["station_rtf_cameras"]
    assert report["closed_loop_chunks"] >= 1  # System 1 ran in the closed loop


def test_model_bench_reports_per_system_params_and_latency():
    report = _bench("--model", "--preset", "tiny")
    text = json.dumps(report)
    assert report["preset"] == "tiny"
    assert "system1" in text and "system2" in text and "system3" in text


def test_precision_without_model_is_refused_by_name():
    result = subprocess.run(
        [sys.executable, "-m", "trivla_drake.cli", "bench", "--set", "precision=bfloat16"],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode != 0 and "precision goes with --model" in result.stderr
