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


def test_the_static_cameras_calibration_puts_each_block_in_the_cell_the_renderer_draws_it_in(station_and_context):
    """station/cameras.camera_calibration + nn/camera_cells: the block's place projects onto its rendered
    pixels, and the image cell the renderer draws it in is the one whose table place is nearest it."""
    from trivla_drake.nn.camera_cells import cell_table_points, rotation_from_rpy
    from trivla_drake.station.cameras import camera_calibration
    from trivla_drake.station.scenario import load_scenario

    cameras = load_scenario().cameras
    calibration = camera_calibration(cameras["static_camera"], "static_camera")
    with pytest.raises(ValueError, match="cameras.wrist_camera rides on"):
        camera_calibration(cameras["wrist_camera"], "wrist_camera")
    station, context = station_and_context
    plant = station.GetSubsystemByName("plant")
    plant_context = plant.GetMyContextFromRoot(context)
    _, labels = _render(station, context, "static_camera")
    places = cell_table_points(calibration, 8, 0.0225)
    x, y, z, roll, pitch, yaw, fx, fy, cx, cy, _, _ = calibration
    for color in ("red", "green", "blue"):
        body = plant.GetBodyByName("block", plant.GetModelInstanceByName(f"block_{color}"))
        position = plant.EvalBodyPoseInWorld(plant_context, body).translation()
        rows, cols = np.nonzero(labels == int(body.index()))
        in_camera = rotation_from_rpy(roll, pitch, yaw).T @ (position - np.array([x, y, z]))
        projected = np.array([fx * in_camera[0] / in_camera[2] + cx, fy * in_camera[1] / in_camera[2] + cy])
        assert np.abs(projected - [cols.mean(), rows.mean()]).max() < 1.5, color
        drawn_in = int(rows.mean() // 28) * 8 + int(cols.mean() // 28)
        assert np.argmin(np.linalg.norm(places[:, :2] - position[:2], axis=1)) == drawn_in, color


def test_the_wrist_cameras_cells_are_placed_from_the_hands_pose_where_the_renderer_draws_the_blocks(station_and_context):
    """station/cameras.hand_camera_calibration + nn/token_anchor.wrist_places: with the arm turned toward
    the blocks, each block is drawn in the wrist view's cell whose table place (computed from the joint
    angles alone) is nearest to it."""
    import torch

    from trivla_drake.nn.camera_cells import camera_pose, cell_rays
    from trivla_drake.nn.panda_tcp import PandaTcpFeatures, denormalize_position
    from trivla_drake.nn.token_anchor import TokenAnchor
    from trivla_drake.station.cameras import hand_camera_calibration
    from trivla_drake.station.scenario import load_scenario

    station, context = station_and_context
    context = context.Clone()
    plant = station.GetSubsystemByName("plant")
    cameras = load_scenario().cameras
    calibration = hand_camera_calibration(plant, cameras["wrist_camera"], "wrist_camera")
    with pytest.raises(ValueError, match="cameras.static_camera rides on 'world'"):
        hand_camera_calibration(plant, cameras["static_camera"], "static_camera")
    rotation, origin = camera_pose(calibration)
    anchor = TokenAnchor(8, torch.zeros(1, 3), wrist_rays=torch.from_numpy(cell_rays(calibration, 8)).float(),
                         wrist_pose=(torch.from_numpy(rotation).float(), torch.from_numpy(origin).float()),
                         plane_height=0.0225)
    plant_context = plant.GetMyContextFromRoot(context)
    panda = plant.GetModelInstanceByName("panda")
    q = plant.GetPositions(plant_context, panda) + np.array([0.2, 0.3, 0.0, 0.2, 0.0, -0.2, 0.0, 0.0, 0.0])
    plant.SetPositions(plant_context, panda, q)
    _, labels = _render(station, context, "wrist_camera")
    places, valid = anchor.wrist_places(PandaTcpFeatures()(torch.from_numpy(q[None, :7]).float()))
    places = denormalize_position(places)[0].numpy()
    assert valid.all()
    for color in ("red", "green", "blue"):
        body = plant.GetBodyByName("block", plant.GetModelInstanceByName(f"block_{color}"))
        position = plant.EvalBodyPoseInWorld(plant_context, body).translation()
        rows, cols = np.nonzero(labels == int(body.index()))
        assert len(rows) > 100, color
        drawn_in = int(rows.mean() // 28) * 8 + int(cols.mean() // 28)
        distances = np.linalg.norm(places[:, :2] - position[:2], axis=1)
        assert np.argmin(distances) == drawn_in and distances[drawn_in] < 0.05, color


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
