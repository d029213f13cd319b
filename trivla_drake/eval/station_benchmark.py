"""Real-time factor of the scripted station with and without its cameras, measured in one run."""

from __future__ import annotations

import copy

from trivla_drake.eval.scripted_run import run_scripted
from trivla_drake.station.scenario import Scenario


def benchmark_station(scenario: Scenario, seconds: float = 4.0, camera_fps: float = 10.0) -> dict:
    """Simulate the scripted run twice: both cameras at `camera_fps`, then no cameras."""
    with_cameras = copy.deepcopy(scenario)
    for camera in with_cameras.cameras.values():
        camera.fps = camera_fps
    without_cameras = copy.deepcopy(scenario)
    without_cameras.cameras = {}
    cameras = run_scripted(with_cameras, seconds)
    bare = run_scripted(without_cameras, seconds)
    return {
        "station_rtf_cameras": cameras.realtime_factor,
        "station_rtf_no_cameras": bare.realtime_factor,
        "station_cameras": sorted(with_cameras.cameras),
        "station_camera_fps": camera_fps,
        "station_sim_seconds": seconds,
        "plant_time_step": scenario.plant_config.time_step,
    }
