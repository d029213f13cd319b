"""RGB cameras from Drake CameraConfigs, rendered headless by RenderEngineVtk and sampled at fps."""

from __future__ import annotations

import math

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import MakeRenderEngineVtk, RenderEngineVtkParams, SceneGraph
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import ScopedName
from pydrake.systems.framework import DiagramBuilder, LeafSystem, OutputPort
from pydrake.systems.sensors import CameraConfig, ImageRgba8U, RgbdSensor


def _frame_named(plant: MultibodyPlant, name: str | None, camera: str):
    if not name or name == "world":
        return plant.world_frame()
    scoped = ScopedName.Parse(name)
    if not plant.HasModelInstanceNamed(scoped.get_namespace()):
        raise ValueError(f"cameras.{camera}.X_PB.base_frame: no model instance '{scoped.get_namespace()}'")
    instance = plant.GetModelInstanceByName(scoped.get_namespace())
    if not plant.HasFrameNamed(scoped.get_element(), instance):
        raise ValueError(f"cameras.{camera}.X_PB.base_frame: no frame '{name}'")
    return plant.GetFrameByName(scoped.get_element(), instance)


class ImageSampleAndHold(LeafSystem):
    """Samples an ImageRgba8U input every `period_s` and at initialisation, and holds it.

    Unlike Drake's ZeroOrderHold it also samples when the simulation is initialised, so a
    consumer reading the image at t = 0 sees the scene rather than a blank frame.
    """

    def __init__(self, period_s: float, width: int, height: int):
        super().__init__()
        model = AbstractValue.Make(ImageRgba8U(width, height))
        self._input = self.DeclareAbstractInputPort("image", model)
        state_index = self.DeclareAbstractState(model)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, 0.0, self._sample)
        self.DeclareInitializationUnrestrictedUpdateEvent(self._sample)
        self.DeclareStateOutputPort("held_image", state_index)
        self._state_index = state_index

    def _sample(self, context, state):
        state.get_mutable_abstract_state(self._state_index).set_value(self._input.Eval(context))


def check_camera_config(name: str, config: CameraConfig) -> None:
    """ValueError naming `cameras.{name}.<field>` for a value the station cannot honour: a frame rate that is not a
    positive finite number, a size below one pixel, or a CameraConfig feature it does not build (depth output,
    a capture offset or output delay, another renderer class, a background other than the VTK renderer's clear
    colour), which would otherwise be ignored without a word."""
    if not (math.isfinite(config.fps) and config.fps > 0):
        raise ValueError(f"cameras.{name}.fps must be a positive, finite number of frames a second, got {config.fps}")
    for field in ("width", "height"):
        if getattr(config, field) < 1:
            raise ValueError(f"cameras.{name}.{field} must be at least 1 pixel, got {getattr(config, field)}")
    unsupported = {
        "depth": (config.depth, "depth images are not rendered (RGB only)"),
        "capture_offset": (config.capture_offset != 0.0, "the held image samples at t = 0, 1/fps, ..."),
        "output_delay": (config.output_delay != 0.0, "images are output when sampled"),
        "renderer_class": (config.renderer_class not in ("", "RenderEngineVtk"), "the renderer is RenderEngineVtk"),
    }
    for field, (given, why) in unsupported.items():
        if given:
            raise ValueError(f"cameras.{name}.{field}: not supported ({why}); leave it out")
    clear = np.asarray(RenderEngineVtkParams().default_clear_color)
    background = np.array([config.background.r(), config.background.g(), config.background.b()])
    if np.abs(background - clear).max() > 1.0 / 255.0 or config.background.a() != 1.0:
        raise ValueError(f"cameras.{name}.background: the renderer clears to {np.round(clear, 3).tolist()} (opaque) "
                         f"for every camera; got {config.background}: leave it out or give that colour")


def add_rgb_camera(
    builder: DiagramBuilder, plant: MultibodyPlant, scene_graph: SceneGraph, name: str, config: CameraConfig
) -> tuple[OutputPort, OutputPort]:
    """Add one camera; returns its ImageRgba8U outputs (held, now): the image sampled every 1/fps
    seconds of sim time and held, and the sensor's own output, rendered at the current state whenever
    it is evaluated (what a periodic consumer such as the policy reads at its tick: never stale)."""
    check_camera_config(name, config)
    renderer = config.renderer_name
    if not scene_graph.HasRenderer(renderer):
        scene_graph.AddRenderer(renderer, MakeRenderEngineVtk(RenderEngineVtkParams()))
    try:
        color_camera, depth_camera = config.MakeCameras()
    except Exception as error:  # Drake's message names the value, not the camera
        raise ValueError(f"cameras.{name}: {error}") from error
    frame = _frame_named(plant, config.X_PB.base_frame, name)
    # X_PB is given in the named frame; RgbdSensor wants the pose in that frame's body.
    X_BodyB = frame.GetFixedPoseInBodyFrame() @ config.X_PB.GetDeterministicValue()
    sensor = builder.AddNamedSystem(
        f"{name}_sensor",
        RgbdSensor(
            parent_id=plant.GetBodyFrameIdOrThrow(frame.body().index()),
            X_PB=X_BodyB,
            color_camera=color_camera,
            depth_camera=depth_camera,
        ),
    )
    builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
    # Only colour is ever evaluated, so depth is never rendered.
    hold = builder.AddNamedSystem(
        f"{name}_sample_and_hold", ImageSampleAndHold(1.0 / config.fps, config.width, config.height)
    )
    builder.Connect(sensor.color_image_output_port(), hold.get_input_port())
    return hold.get_output_port(), sensor.color_image_output_port()
