"""The station's scenario: a typed dataclass loaded from a `*.scenarios.yaml` file (Drake style)."""


import dataclasses as dc
import os
from pathlib import Path

from pydrake.common.yaml import yaml_load_typed
from pydrake.multibody.parsing import ModelDirective
from pydrake.multibody.plant import MultibodyPlantConfig
from pydrake.systems.analysis import SimulatorConfig
from pydrake.systems.sensors import CameraConfig
from pydrake.visualization import VisualizationConfig


@dc.dataclass
class PandaDriverConfig:
    """Joint-level PD gains of the Panda driver (implicit PD in the plant + gravity compensation)."""

    # Proportional gains of the seven arm joints [N m / rad].
    arm_kp: list[float] = dc.field(
        default_factory=lambda: [1200.0, 1200.0, 1200.0, 1200.0, 500.0, 400.0, 200.0]
    )
    # Derivative gains of the seven arm joints [N m s / rad].
    arm_kd: list[float] = dc.field(
        default_factory=lambda: [100.0, 100.0, 100.0, 100.0, 40.0, 30.0, 15.0]
    )
    # Proportional gain of each finger [N / m]; the squeeze force is kp times the width error.
    finger_kp: float = 400.0
    # Derivative gain of each finger [N s / m].
    finger_kd: float = 20.0


@dc.dataclass
class Scenario:
    """Everything that defines a station; every field has a default except the directives."""

    # Seed for anything random in the station itself (none today; tasks seed their own).
    random_seed: int = 0
    # The MultibodyPlant: time step [s], contact model, discrete solver approximation.
    plant_config: MultibodyPlantConfig = dc.field(
        default_factory=lambda: MultibodyPlantConfig(
            time_step=0.004,
            contact_model="hydroelastic_with_fallback",
            discrete_contact_approximation="lagged",
        )
    )
    # Drake model directives: the models, their welds and default poses. The Panda must be named
    # `panda`; packages `trivla_panda` (converted Panda) and `trivla_drake_models` (models/) exist.
    directives: list[ModelDirective] = dc.field(default_factory=list)
    # Cameras by name; RGB is rendered with RenderEngineVtk at each camera's fps.
    cameras: dict[str, CameraConfig] = dc.field(default_factory=dict)
    # Meshcat visualisation (used only when a Meshcat is given).
    visualization: VisualizationConfig = dc.field(default_factory=VisualizationConfig)
    # The Panda's joint-level driver.
    panda_driver: PandaDriverConfig = dc.field(default_factory=PandaDriverConfig)
    # Integrator settings for the Simulator that runs the station.
    simulator_config: SimulatorConfig = dc.field(
        default_factory=lambda: SimulatorConfig(target_realtime_rate=0.0, publish_every_time_step=False)
    )


class ScenarioError(ValueError):
    """A scenario file that cannot be read or names something that does not exist."""


def models_dir() -> Path:
    """The project's `models/` folder (override with the TRIVLA_DRAKE_MODELS environment variable)."""
    path = Path(os.environ.get("TRIVLA_DRAKE_MODELS", Path(__file__).resolve().parents[2] / "models"))
    if not path.is_dir():
        raise FileNotFoundError(
            f"models folder not found at {path}; install trivla-drake from its source tree "
            "(pip install -e .) or set TRIVLA_DRAKE_MODELS"
        )
    return path


def default_scenario_file() -> Path:
    """The scenario file shipped in models/."""
    return models_dir() / "default.scenarios.yaml"


def load_scenario(filename: "str | os.PathLike | None" = None, scenario_name: str = "default") -> Scenario:
    """Load `scenario_name` from a scenarios YAML file; errors name the file and the field."""
    filename = Path(filename) if filename is not None else default_scenario_file()
    if not filename.is_file():
        raise ScenarioError(f"scenario file {filename} does not exist")
    try:
        return yaml_load_typed(
            schema=Scenario, filename=str(filename), child_name=scenario_name, defaults=Scenario()
        )
    except Exception as error:  # Drake raises RuntimeError with the YAML key path in the text.
        raise ScenarioError(f"cannot load scenario '{scenario_name}' from {filename}: {error}") from error


# A held camera sampled this rarely [fps] renders at initialisation only (within any episode's length).
RARELY_HELD_FPS = 1e-3


def with_cameras_held_rarely(scenario: Scenario) -> Scenario:
    """A copy of `scenario` whose cameras' held `.rgb_image` ports sample only at initialisation: for
    loops whose readers take `.rgb_image_now` (rendered on demand), so the periodic hold does not render
    10 frames a second that nobody reads (about a fifth of the closed loop's time on 2 cores)."""
    import copy

    scenario = copy.deepcopy(scenario)  # its Drake members copy through their serialisers
    for camera in scenario.cameras.values():
        camera.fps = RARELY_HELD_FPS
    return scenario


def make_simulator(diagram, scenario: Scenario):
    """A Simulator of `diagram` (a station built from `scenario`, alone or in a larger diagram) with the
    scenario's `simulator_config` applied (integrator, real-time rate, publishing)."""
    from pydrake.systems.analysis import ApplySimulatorConfig, Simulator

    simulator = Simulator(diagram)
    ApplySimulatorConfig(scenario.simulator_config, simulator)
    return simulator
