"""`TabletopEnv`: the station closed through the diff-IK and the action executor, one action per step.

    action (7) -> ActionExecutor (36 Hz) -> ee_target -> DifferentialIKSystem (100 Hz) -> panda.position
                                       \\-> gripper_width -------------------------------> panda.gripper_width

Observations are dicts:
    state           float (18,)   panda.state: q (7 arm, 2 fingers) then v
    static_rgb,     uint8 (H, W, 3), rendered at the current state (only when the env has cameras)
    wrist_rgb
    ee_target       float (4, 4)  the executor's commanded tcp pose (what actions are relative to)
    gripper_command float         +1 open / -1 closed, the executor's current gripper command
    tcp_pose        float (4, 4)  measured pose of panda_hand_tcp in the world
    time            float         simulated time [s]
"""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import DiagramBuilder

from trivla_drake.station.scenario import Scenario, load_scenario, make_simulator, with_cameras_held_rarely
from trivla_drake.station.station import make_station
from trivla_drake.systems.action_executor import DEFAULT_ACTION_SPACE, ActionExecutor, ActionSpace, check_action
from trivla_drake.systems.diffik_system import DifferentialIKSystem
from trivla_drake.tasks.scene import Layout, SceneSpec, SceneState
from trivla_drake.tasks.sim import StationHandles

CAMERA_KEYS = {"static_camera": "static_rgb", "wrist_camera": "wrist_rgb"}


class SimulationError(RuntimeError):
    """The simulation failed (a solver error, or a non-finite state)."""


class TabletopEnv:
    """The tabletop at the policy's control rate; `reset` starts an episode (or a chain).

    `image_size` None runs without cameras (physics only, much faster); an int renders both cameras
    at that square size. The Diagram is built once and reused: `reset` starts from a new Context
    (every state at its default) and gives the diff-IK a fresh OSQP solver (whose adaptive internals
    live outside the Context), so an episode's outcome does not depend on the episodes before it.
    Rebuilding the Diagram per episode instead would cost 0.3 s and about 9 MB that Drake does not
    give back (20 MB with cameras).
    """

    def __init__(
        self,
        scenario: Scenario | None = None,
        *,
        image_size: int | None = None,
        action_space: ActionSpace = DEFAULT_ACTION_SPACE,
    ):
        self._scenario_source = scenario
        self.image_size = image_size
        self.action_space = action_space
        self._step_index = 0
        self._simulator = None
        self._started = False

    # ---------------------------------------------------------------- building
    def _scenario(self) -> Scenario:
        # The env renders on demand at each control step (an image shows the same instant as the state).
        scenario = load_scenario() if self._scenario_source is None else self._scenario_source
        scenario = with_cameras_held_rarely(scenario)
        if self.image_size is None:
            scenario.cameras = {}
        for camera in scenario.cameras.values():
            camera.width = camera.height = int(self.image_size)
        return scenario

    def _build(self) -> None:
        builder = DiagramBuilder()
        self._built_scenario = self._scenario()
        station = builder.AddNamedSystem("station", make_station(self._built_scenario))
        diffik = builder.AddNamedSystem("diffik", DifferentialIKSystem(warn_tracking=False))
        executor = builder.AddNamedSystem("executor", ActionExecutor(self.action_space))
        state = station.GetOutputPort("panda.state")
        builder.Connect(state, diffik.GetInputPort("robot_state"))
        builder.Connect(state, executor.GetInputPort("robot_state"))
        builder.Connect(executor.GetOutputPort("ee_target"), diffik.GetInputPort("ee_target"))
        builder.Connect(diffik.GetOutputPort("position_setpoint"), station.GetInputPort("panda.position"))
        builder.Connect(executor.GetOutputPort("gripper_width"), station.GetInputPort("panda.gripper_width"))
        builder.ExportInput(executor.GetInputPort("action"), "action")
        self.diagram = builder.Build()
        self.station, self.executor, self.diffik = station, executor, diffik
        self.handles = StationHandles(station)
        self._simulator = make_simulator(self.diagram, self._built_scenario)
        self._context = self._simulator.get_mutable_context()
        self._cameras = {}
        for name, key in CAMERA_KEYS.items():
            if self.image_size is not None and station.HasSubsystemNamed(f"{name}_sensor"):
                sensor = station.GetSubsystemByName(f"{name}_sensor")
                self._cameras[key] = (sensor, sensor.color_image_output_port())

    def layout(self) -> Layout:
        """The fixtures' poses (builds the station on first use)."""
        if self._simulator is None:
            self._build()
        return self.handles.layout(self._context)

    # ---------------------------------------------------------------- stepping
    def reset(self, spec: SceneSpec) -> dict:
        """Start from `spec` (a fresh Context at time 0); returns the first observation."""
        if self._simulator is None:
            self._build()
        else:  # a fresh Context (every state at its default, time 0) and a fresh diff-IK solver
            self._simulator = make_simulator(self.diagram, self._built_scenario)
            self._context = self._simulator.get_mutable_context()
        self.handles.apply(self._context, spec)
        self.diagram.GetInputPort("action").FixValue(self._context, np.zeros(7))
        self._simulator.Initialize()
        self._step_index = 0
        self._started = True
        return self.observation()

    def step(self, action, *, images: bool = True) -> dict:
        """Apply one action for one control period; returns the next observation (without the camera
        images when `images` is False: rendering is most of a step's cost; `images()` adds them later)."""
        if not self._started:
            raise RuntimeError("TabletopEnv.step called before reset")
        action = check_action(action)
        self.diagram.GetInputPort("action").FixValue(self._context, action)
        self._step_index += 1
        try:
            self._simulator.AdvanceTo(self._step_index * self.action_space.dt)
        except RuntimeError as error:
            raise SimulationError(f"simulation failed at t = {self._context.get_time():.3f} s: {error}") from error
        plant_context = self.handles.plant.GetMyContextFromRoot(self._context)
        if not np.all(np.isfinite(self.handles.plant.GetPositionsAndVelocities(plant_context))):
            raise SimulationError(f"non-finite state at t = {self._context.get_time():.3f} s")
        return self.observation(images=images)

    @property
    def step_index(self) -> int:
        return self._step_index

    @property
    def last_action(self) -> np.ndarray:
        """The action the last step applied (zeros after `reset`): a copy, (7,)."""
        if not self._started:
            raise RuntimeError("TabletopEnv.last_action read before reset")
        return np.array(self.diagram.GetInputPort("action").Eval(self._context), dtype=float)

    def scene(self) -> SceneState:
        """Ground truth of the scene now."""
        return self.handles.read(self._context)

    def observation(self, *, images: bool = True) -> dict:
        """The policy-facing observation now (see the module docstring); `images=False` leaves out
        the camera images."""
        station_context = self.station.GetMyContextFromRoot(self._context)
        executor_context = self.executor.GetMyContextFromRoot(self._context)
        width = self.executor.GetOutputPort("gripper_width").Eval(executor_context)[0]
        plant = self.handles.plant
        obs = {
            "state": np.array(self.station.GetOutputPort("panda.state").Eval(station_context)),
            "ee_target": self.executor.commanded_pose(executor_context),
            "gripper_command": 1.0 if width > 0.04 else -1.0,
            "tcp_pose": self.handles.tcp_frame.CalcPoseInWorld(plant.GetMyContextFromRoot(self._context)).GetAsMatrix4(),
            "time": self._context.get_time(),
        }
        if images:
            obs.update(self.images())
        return obs

    @property
    def has_cameras(self) -> bool:
        """Whether observations carry camera images (image_size was given)."""
        return bool(self._cameras)

    def images(self) -> dict[str, np.ndarray]:
        """Each camera's RGB image now, rendered on this call: {key: (H, W, 3) uint8}."""
        out = {}
        for key, (sensor, port) in self._cameras.items():
            image = port.Eval(sensor.GetMyContextFromRoot(self._context))
            out[key] = np.array(image.data[:, :, :3], dtype=np.uint8)
        return out
