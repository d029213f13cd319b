"""Shared fixtures: the default scenario, and a closed-loop station with a settable target."""

from __future__ import annotations

import logging

import numpy as np
import pytest

logging.getLogger("drake").setLevel(logging.ERROR)


@pytest.fixture(scope="module", autouse=True)
def _one_torch_thread():
    """Tests' models are small: threads buy nothing, and on a busy 2-core machine OpenMP threads
    stall each other. Restored after each module."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def scenario():
    from trivla_drake.station.scenario import load_scenario

    return load_scenario()


class ClosedLoop:
    """Station + DifferentialIKSystem with `ee_target` and `gripper_width` as fixed inputs."""

    def __init__(self, scenario):
        from pydrake.systems.analysis import Simulator
        from pydrake.systems.framework import DiagramBuilder

        from trivla_drake.station.station import make_station
        from trivla_drake.systems.diffik_system import DifferentialIKSystem

        builder = DiagramBuilder()
        self.station = builder.AddNamedSystem("station", make_station(scenario))
        self.diffik = builder.AddNamedSystem("diffik", DifferentialIKSystem())
        builder.Connect(self.station.GetOutputPort("panda.state"), self.diffik.GetInputPort("robot_state"))
        builder.Connect(self.diffik.GetOutputPort("position_setpoint"), self.station.GetInputPort("panda.position"))
        builder.ExportInput(self.diffik.GetInputPort("ee_target"), "ee_target")
        builder.ExportInput(self.station.GetInputPort("panda.gripper_width"), "gripper_width")
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        self.plant = self.station.GetSubsystemByName("plant")
        self.plant_context = self.plant.GetMyContextFromRoot(self.context)

    def go(self, position, width, seconds, rpy=(np.pi, 0.0, 0.0)):
        """Hold a hand target (pointing down by default) and gripper width for `seconds`."""
        from pydrake.math import RigidTransform, RollPitchYaw

        target = RigidTransform(RollPitchYaw(rpy), np.asarray(position, dtype=float))
        self.diagram.GetInputPort("ee_target").FixValue(self.context, target)
        self.diagram.GetInputPort("gripper_width").FixValue(self.context, [width])
        self.simulator.AdvanceTo(self.context.get_time() + seconds)

    def tcp_position(self):
        return self.plant.GetFrameByName("panda_hand_tcp").CalcPoseInWorld(self.plant_context).translation()

    def body_position(self, model, body):
        instance = self.plant.GetModelInstanceByName(model)
        return self.plant.EvalBodyPoseInWorld(self.plant_context, self.plant.GetBodyByName(body, instance)).translation()

    def output(self, name):
        return self.station.GetOutputPort(name).Eval(self.station.GetMyContextFromRoot(self.context))


@pytest.fixture
def closed_loop(scenario):
    scenario.cameras = {}  # physics-only tests need no rendering
    return ClosedLoop(scenario)


@pytest.fixture(scope="session")
def saved(tmp_path_factory):
    """(model, directory): an untrained tiny TriVLA with normalisation statistics, saved in float32.
    Tests copy the directory before damaging it."""
    from trivla_drake.nn.checkpoint import save_checkpoint
    from trivla_drake.nn.presets import make_config
    from trivla_drake.nn.normalization import NormalizationStats
    from trivla_drake.nn.trivla import TriVLA
    import torch

    directory = str(tmp_path_factory.mktemp("ckpt"))
    model = TriVLA(make_config("tiny", init_seed=3)).eval()
    # Weights no fresh model of that config has (a loader that rebuilt from config.json's init_seed and skipped the
    # weights file would otherwise load an identical model).
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(0.01 * torch.randn(parameter.shape, generator=generator))
    rng = np.random.default_rng(0)
    model.set_normalization(
        NormalizationStats.from_data(rng.normal(size=(50, 18)), rng.uniform(-0.05, 0.05, size=(50, 10, 7)))
    )
    save_checkpoint(model, directory)
    return model, directory
