"""Cameras render headless, in colour, and their images change where the robot moves."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def station_and_context():
    from trivla_drake.station.scenario import load_scenario
    from trivla_drake.station.station import make_station

    station = make_station(load_scenario())
    return station, station.CreateDefaultContext()


def _render(station, context, camera):
    sensor = station.GetSubsystemByName(f"{camera}_sensor")
    sensor_context = sensor.GetMyContextFromRoot(context)
    rgb = sensor.color_image_output_port().Eval(sensor_context).data[:, :, :3].copy()
    labels = sensor.label_image_output_port().Eval(sensor_context).data[:, :, 0].copy()
    return rgb, labels


def _panda_labels(plant):
    """Render labels are body indices: the Panda's are those of its model instance."""
    return [int(i) for i in plant.GetBodyIndices(plant.GetModelInstanceByName("panda"))]


def test_renders_without_a_display(station_and_context, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    from pydrake.systems.analysis import Simulator

    station, context = station_and_context
    simulator = Simulator(station, context.Clone())
    simulator.Initialize()  # the held image is sampled at initialisation, not blank until t = 0.1 s
    image = station.GetOutputPort("static_camera.rgb_image").Eval(simulator.get_context())
    assert (image.width(), image.height()) == (224, 224)
    assert image.data[:, :, :3].std() > 10  # a scene, not a blank frame


def test_colours_reach_the_images(station_and_context):
    station, context = station_and_context
    plant = station.GetSubsystemByName("plant")
    rgb, labels = _render(station, context, "static_camera")
    red_block = int(plant.GetBodyByName("block", plant.GetModelInstanceByName("block_red")).index())
    red = rgb[labels == red_block].astype(float)
    assert len(red) > 20
    assert red[:, 0].mean() > 2 * red[:, 1].mean() and red[:, 0].mean() > 2 * red[:, 2].mean()
    # The Panda's converted visual meshes are drawn (labels present) and mostly white.
    panda = np.isin(labels, _panda_labels(plant))
    assert panda.sum() > 100
    assert np.median(rgb[panda].mean(axis=1)) > 120


def test_images_change_where_the_robot_moves(station_and_context):
    station, context = station_and_context
    context = context.Clone()
    plant = station.GetSubsystemByName("plant")
    plant_context = plant.GetMyContextFromRoot(context)
    panda = plant.GetModelInstanceByName("panda")
    before = {cam: _render(station, context, cam) for cam in ("static_camera", "wrist_camera")}
    q = plant.GetPositions(plant_context, panda)
    q[0] += 0.4  # swing the arm about its base
    q[3] += 0.3
    plant.SetPositions(plant_context, panda, q)
    after = {cam: _render(station, context, cam) for cam in ("static_camera", "wrist_camera")}

    rgb0, labels0 = before["static_camera"]
    rgb1, labels1 = after["static_camera"]
    changed = np.abs(rgb1.astype(int) - rgb0.astype(int)).max(axis=2) > 30
    robot = np.isin(labels0, _panda_labels(plant)) | np.isin(labels1, _panda_labels(plant))
    assert changed.sum() > 200
    # Every pixel that changed shows the robot before or after (shading at its silhouette aside).
    assert (changed & robot).sum() >= 0.97 * changed.sum()
    # The wrist camera rides on the hand: its whole view moves.
    wrist_change = np.abs(after["wrist_camera"][0].astype(int) - before["wrist_camera"][0].astype(int))
    assert (wrist_change.max(axis=2) > 30).mean() > 0.2


def test_a_scenario_with_cameras_held_rarely_is_a_copy_and_keeps_the_live_ports():
    """Loops whose policy reads `.rgb_image_now` sample the held images at initialisation only; the caller's
    scenario keeps its fps."""
    from pydrake.systems.analysis import Simulator

    from trivla_drake.station.scenario import RARELY_HELD_FPS, load_scenario, with_cameras_held_rarely
    from trivla_drake.station.station import make_station

    scenario = load_scenario()
    rare = with_cameras_held_rarely(scenario)
    assert [c.fps for c in scenario.cameras.values()] == [10.0, 10.0]
    assert [c.fps for c in rare.cameras.values()] == [RARELY_HELD_FPS] * 2
    station = make_station(rare)
    simulator = Simulator(station)
    simulator.Initialize()
    image = station.GetOutputPort("static_camera.rgb_image_now").Eval(simulator.get_context())
    assert (image.width(), image.height()) == (224, 224) and image.data[:, :, :3].std() > 10


def test_make_simulator_applies_the_scenarios_simulator_config():
    from pydrake.systems.analysis import ExtractSimulatorConfig

    from trivla_drake.station import load_scenario, make_simulator, make_station

    scenario = load_scenario()
    scenario.cameras = {}
    scenario.simulator_config.max_step_size = 0.01
    scenario.simulator_config.publish_every_time_step = True
    applied = ExtractSimulatorConfig(make_simulator(make_station(scenario), scenario))
    assert applied.max_step_size == 0.01 and applied.publish_every_time_step
