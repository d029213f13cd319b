"""The policy added to a flat diagram of one's own through the public API: port objects instead of a station,
the base's pose read from the plant, and the Drake-style TriVLAPolicyConfig loaded from YAML."""

# No `from __future__ import annotations`: UserScenario below is read by Drake's YAML loader, which needs real types.

import dataclasses as dc
import subprocess
import sys

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.common.yaml import yaml_load_typed
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

import trivla_drake
from trivla_drake import (
    ApplyTriVLAPolicyConfig,
    PolicyRates,
    TriVLAPolicyConfig,
    add_trivla_policy,
    drake_panda_urdf,
    make_parser,
    robot_base_pose,
)
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA
from test_user_diagram_frames import MOVED, load_example


@pytest.fixture(scope="module")
def tiny_model():
    return TriVLA(make_config("tiny")).eval()


def _user_world(model):
    builder = DiagramBuilder()
    world = load_example().add_user_world(builder, MOVED, image_size=model.image_size)
    return builder, world


def _ports(world):
    return dict(static_camera=world.static_camera, wrist_camera=world.wrist_camera, robot_state=world.robot_state,
                arm_position=world.arm_position, gripper_width=world.gripper_width)


def _simulate(builder, world, policy, seconds):
    source = builder.AddSystem(ConstantValueSource(AbstractValue.Make("lift the red block")))
    builder.Connect(source.get_output_port(), policy.GetInputPort("instruction"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.Initialize()
    context = simulator.get_mutable_context()
    plant_context = world.plant.GetMyContextFromRoot(context)
    hand = world.plant.GetFrameByName("panda_hand_tcp", world.panda)
    target = policy.GetOutputPort("ee_target").Eval(policy.GetMyContextFromRoot(context)).GetAsMatrix4()
    np.testing.assert_allclose(target, hand.CalcPoseInWorld(plant_context).GetAsMatrix4(), atol=1e-6)
    q_start = world.robot_state.Eval(plant_context)[:7].copy()
    simulator.AdvanceTo(seconds)
    return diagram, context, q_start, world.robot_state.Eval(plant_context)[:7]


def test_port_objects_of_a_flat_diagram_with_the_base_read_from_the_plant(tiny_model):
    builder, world = _user_world(tiny_model)
    X_WB = robot_base_pose(world.plant, world.panda)
    assert X_WB.IsNearlyEqualTo(MOVED, 1e-12)
    policy = add_trivla_policy(builder, None, tiny_model, X_WB=X_WB, **_ports(world))
    diagram, context, q_start, q_end = _simulate(builder, world, policy, 0.3)
    chunk = policy.GetOutputPort("action_chunk").Eval(policy.GetMyContextFromRoot(context))
    assert chunk.shape == (10, 7) and np.abs(q_end - q_start).max() > 1e-3  # an untrained policy still moves it
    diffik = diagram.GetSubsystemByName("trivla_policy_diffik")
    assert diffik.GetOutputPort("tracking_error").Eval(diffik.GetMyContextFromRoot(context))[0] < 0.05


def test_port_names_need_a_station_that_has_them(tiny_model):
    builder, world = _user_world(tiny_model)
    ports = _ports(world)
    with pytest.raises(ValueError, match="static_camera='static_camera.rgb_image_now' names a port but station is "):
        add_trivla_policy(builder, None, tiny_model, **{**ports, "static_camera": "static_camera.rgb_image_now"})
    with pytest.raises(ValueError, match=r"robot_state: 'plant' has no output port 'panda.state'; its output ports"):
        add_trivla_policy(builder, world.plant, tiny_model, **{**ports, "robot_state": "panda.state"})
    with pytest.raises(TypeError, match="arm_position must be a port name .* or an InputPort, got LeafOutputPort"):
        add_trivla_policy(builder, None, tiny_model, **{**ports, "arm_position": world.robot_state})
    with pytest.raises(TypeError, match="X_WB must be a pydrake.math.RigidTransform"):
        add_trivla_policy(builder, None, tiny_model, X_WB=MOVED.GetAsMatrix4(), **ports)


def test_robot_base_pose_needs_a_finalized_plant_and_a_welded_base():
    plant = MultibodyPlant(time_step=0.0)
    (panda,) = make_parser(plant).AddModels(str(drake_panda_urdf()))
    with pytest.raises(ValueError, match="Finalize"):
        robot_base_pose(plant, panda)
    plant.Finalize()  # panda_link0 left floating
    with pytest.raises(ValueError, match="panda::panda_link0 is not welded to the world"):
        robot_base_pose(plant, panda)
    with pytest.raises(ValueError, match="no frame 'base_link'"):
        robot_base_pose(plant, panda, "base_link")


@dc.dataclass
class UserScenario:
    """A user's own scenario with the policy as one of its fields, as in Drake's hardware_sim."""

    policy: TriVLAPolicyConfig = dc.field(default_factory=TriVLAPolicyConfig)


def test_the_config_from_yaml_builds_the_policy(saved):
    _, checkpoint = saved
    scenario = yaml_load_typed(schema=UserScenario, data=f"""
policy:
  checkpoint: {checkpoint}
  policy_period_s: 0.25
  latency_mode: fixed
  latency_seconds: 0.05
  seed: 3
  base_frame: panda::panda_link0
  name: my_policy
""")
    config = scenario.policy
    assert config.policy_rates().policy_period_s == 0.25 and config.policy_rates().latency.seconds == 0.05
    builder, world = _user_world(saved[0])
    policy = ApplyTriVLAPolicyConfig(config, builder, plant=world.plant, **_ports(world))
    assert policy.get_name() == "my_policy"
    assert policy.systems["policy"].period_s == 0.25
    _simulate(builder, world, policy, 0.0)  # ee_target starts at the hand, in the world: the base was read


def test_the_default_config_is_the_default_rates_and_the_origin():
    config = TriVLAPolicyConfig()
    assert config.policy_rates() == PolicyRates()
    assert config.base_pose(None).IsExactlyIdentity()
    moved = "X_WB: {translation: [0.3, -0.2, 0.1], rotation: !Rpy {deg: [0, 0, 90]}}"
    assert yaml_load_typed(schema=TriVLAPolicyConfig, data=moved).base_pose(None).IsNearlyEqualTo(MOVED, 1e-12)


def test_a_typo_in_the_yaml_is_refused_naming_the_field():
    with pytest.raises(RuntimeError, match="chekpoint"):
        yaml_load_typed(schema=TriVLAPolicyConfig, data="chekpoint: models/trivla_cpu")


@pytest.mark.parametrize("fields, match", [
    (dict(latency_mode="slow"), "TriVLAPolicyConfig.latency_mode"),
    (dict(policy_period_s=0.0), "TriVLAPolicyConfig.policy_period_s must be a positive number"),
    (dict(base_frame="robot::panda_link0"), "TriVLAPolicyConfig.base_frame 'robot::panda_link0': no model instance"),
    (dict(base_frame="panda::panda_hand"), "TriVLAPolicyConfig.base_frame 'panda::panda_hand': .*not welded"),
    (dict(base_frame="panda::panda_link0", X_WB="{translation: [0, 0, 0.1]}"), "give X_WB or base_frame, not both"),
    (dict(X_WB="{base_frame: panda::panda_hand}"), "TriVLAPolicyConfig.X_WB.base_frame must be 'world'"),
    (dict(checkpoint="/somewhere"), r"checkpoint \('/somewhere'\) and model= both"),
])
def test_bad_config_values_name_the_field(tiny_model, fields, match):
    yaml = "\n".join(f"{key}: {value}" for key, value in fields.items())
    config = yaml_load_typed(schema=TriVLAPolicyConfig, data=yaml)
    builder, world = _user_world(tiny_model)
    with pytest.raises(ValueError, match=match):
        ApplyTriVLAPolicyConfig(config, builder, plant=world.plant, model=tiny_model, **_ports(world))


def test_base_frame_needs_the_plant(tiny_model):
    with pytest.raises(ValueError, match="base_frame 'panda::panda_link0' is read from a plant: pass plant="):
        ApplyTriVLAPolicyConfig(TriVLAPolicyConfig(base_frame="panda::panda_link0"), DiagramBuilder(),
                                model=tiny_model)


def test_the_public_api_imports_from_the_package_without_loading_drake_or_torch():
    for name in trivla_drake.__all__:
        assert getattr(trivla_drake, name) is not None
    check = ("import sys, trivla_drake; "
             "assert not {'pydrake', 'torch'} & {name.split('.')[0] for name in sys.modules}, 'imported eagerly'")
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
