"""`make_station(scenario)`: the simulated world as one Drake Diagram with named ports.

Exported ports (`{instance}.{port}`, as in manipulation's MakeHardwareStation):
  inputs
    panda.position        7-vector, arm joint setpoints [rad]
    panda.gripper_width   1-vector, desired distance between the fingers [m], 0 to 0.08
  outputs
    panda.state           18-vector [q (7 arm, 2 fingers) [rad, m]; v [rad/s, m/s]]
    plant.state           the whole plant's state (for task predicates)
    plant.body_poses      list of RigidTransform, world frame, indexed by BodyIndex
    lamp.on               1-vector, 1 while the button's lamp is lit
    {camera}.rgb_image    ImageRgba8U for every camera in the scenario, sampled at its fps and held
                          (for recorders and viewers: up to 1/fps old)
    {camera}.rgb_image_now  ImageRgba8U of the same camera rendered at the current state when
                          evaluated (for periodic consumers such as the policy, which read it at
                          their own ticks; nothing renders it otherwise)
    query_object          SceneGraph's QueryObject
"""

from __future__ import annotations

import math

import numpy as np
from pydrake.geometry import Meshcat
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import ModelDirectives, Parser, ProcessModelDirectives
from pydrake.multibody.plant import AddMultibodyPlant
from pydrake.multibody.tree import PdControllerGains
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.visualization import ApplyVisualizationConfig

from trivla_drake.robot.panda_assets import PACKAGE_NAME, drake_panda_dir, drake_panda_urdf
from trivla_drake.station.button_lamp import ButtonLampLogic
from trivla_drake.station.cameras import add_rgb_camera
from trivla_drake.station.panda_driver import add_panda_driver, make_panda_only_plant
from trivla_drake.station.scenario import Scenario, ScenarioError, models_dir

MODELS_PACKAGE = "trivla_drake_models"


def make_parser(plant) -> Parser:
    """A Parser that knows the `trivla_panda` and `trivla_drake_models` packages."""
    parser = Parser(plant)
    parser.package_map().Add(PACKAGE_NAME, str(drake_panda_dir()))
    parser.package_map().Add(MODELS_PACKAGE, str(models_dir()))
    return parser


def _add_models(scenario: Scenario, plant, parser: Parser) -> None:
    # Check every model file first, so a typo is reported with its directive, not deep in Drake.
    for index, directive in enumerate(scenario.directives):
        if directive.add_model is None:
            continue
        try:
            parser.package_map().ResolveUrl(directive.add_model.file)
        except Exception as error:
            raise ScenarioError(
                f"scenario directives[{index}].add_model (name '{directive.add_model.name}'): "
                f"cannot find file '{directive.add_model.file}': {error}"
            ) from error
    try:
        ProcessModelDirectives(ModelDirectives(directives=scenario.directives), plant, parser)
    except Exception as error:
        raise ScenarioError(f"scenario directives: {error}") from error
    if not plant.HasModelInstanceNamed("panda"):
        raise ScenarioError("scenario directives: no model named 'panda' (the station drives it)")


def _check_base_at_origin(plant, panda) -> None:
    """ScenarioError unless `panda_link0` is welded to the world at the origin: the diff-IK, the actions and the
    policy's tool-centre point are all computed in the Panda's base frame, taken to be the world's."""
    base = plant.GetBodyByName("panda_link0", panda)
    if base.index() not in [body.index() for body in plant.GetBodiesWeldedTo(plant.world_body())]:
        raise ScenarioError("scenario directives: panda::panda_link0 must be welded to the world (add_weld)")
    X_WB = plant.EvalBodyPoseInWorld(plant.CreateDefaultContext(), base)
    if not X_WB.IsNearlyEqualTo(RigidTransform(), 1e-9):
        raise ScenarioError(
            "scenario directives: panda::panda_link0 must be welded at the world origin, unrotated (the diff-IK, the "
            f"actions and the policy's hand poses are in the Panda's base frame, taken as the world's); it is at "
            f"{np.round(X_WB.translation(), 4).tolist()} m: move the other models instead, or build a world of your own "
            "and pass the base pose to add_trivla_policy(X_WB=...) (examples/user_diagram.py)")


def make_station(scenario: Scenario, *, meshcat: Meshcat | None = None) -> Diagram:
    """Build the station Diagram for `scenario`; with `meshcat`, it is also drawn there."""
    time_step = scenario.plant_config.time_step
    if not (math.isfinite(time_step) and time_step >= 0):  # Drake would abort the process
        raise ScenarioError(f"plant_config.time_step must be a finite number of seconds >= 0, got {time_step}")
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(scenario.plant_config, builder)
    parser = make_parser(plant)
    _add_models(scenario, plant, parser)
    plant.Finalize()

    panda = plant.GetModelInstanceByName("panda")
    _check_base_at_origin(plant, panda)
    controller_plant = make_panda_only_plant(str(drake_panda_urdf()), parser)
    arm_input, gripper_input = add_panda_driver(
        builder, plant, panda, controller_plant, scenario.panda_driver
    )
    builder.ExportInput(arm_input, "panda.position")
    builder.ExportInput(gripper_input, "panda.gripper_width")
    builder.ExportOutput(plant.get_state_output_port(panda), "panda.state")
    builder.ExportOutput(plant.get_state_output_port(), "plant.state")
    builder.ExportOutput(plant.get_body_poses_output_port(), "plant.body_poses")
    builder.ExportOutput(scene_graph.get_query_output_port(), "query_object")

    if plant.HasModelInstanceNamed("button"):
        button = plant.GetModelInstanceByName("button")
        # The cap's PD is its return spring; the lamp's PD lifts it to the logic's target.
        for joint, kp, kd in (("button_press", 300.0, 5.0), ("lamp_lift", 50.0, 2.0)):
            plant.GetJointActuatorByName(joint, button).set_controller_gains(PdControllerGains(p=kp, d=kd))
        logic = builder.AddNamedSystem("button_lamp_logic", ButtonLampLogic())
        builder.Connect(plant.get_state_output_port(button), logic.get_input_port())
        builder.Connect(logic.GetOutputPort("desired_state"), plant.get_desired_state_input_port(button))
        builder.ExportOutput(logic.GetOutputPort("lamp_on"), "lamp.on")

    for name, camera in scenario.cameras.items():
        held, now = add_rgb_camera(builder, plant, scene_graph, name, camera)
        builder.ExportOutput(held, f"{name}.rgb_image")
        builder.ExportOutput(now, f"{name}.rgb_image_now")

    if meshcat is not None:
        ApplyVisualizationConfig(scenario.visualization, builder, meshcat=meshcat)

    diagram = builder.Build()
    diagram.set_name("station")
    _warm_up_renderers(diagram, scenario)
    return diagram


def _warm_up_renderers(diagram: Diagram, scenario: Scenario) -> None:
    """Render each camera once. VTK's very first frame differs from every later one in a few
    pixels; absorbing it here keeps rollouts bit-identical across Contexts and re-runs."""
    if not scenario.cameras:
        return
    context = diagram.CreateDefaultContext()
    for name in scenario.cameras:
        sensor = diagram.GetSubsystemByName(f"{name}_sensor")
        sensor.color_image_output_port().Eval(sensor.GetMyContextFromRoot(context))
