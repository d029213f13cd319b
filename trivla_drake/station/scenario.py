"""The station's scenario: a typed dataclass loaded from a `*.scenarios.yaml` file (Drake style)."""


import dataclasses as dc
import logging
import math
import os
import re
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
        scenario = yaml_load_typed(
            schema=Scenario, filename=str(filename), child_name=scenario_name, defaults=Scenario()
        )
    except Exception as error:  # Drake's loader raises bare TypeErrors, KeyErrors, ... on a bad or cut-short file.
        raise ScenarioError(_why_not_loaded(filename, scenario_name, error)) from error
    check_plant_config(scenario.plant_config, f"scenario '{scenario_name}' in {filename}: plant_config")
    return scenario


def _why_not_loaded(filename: Path, scenario_name: str, error: Exception) -> str:
    """What is wrong with a scenarios file Drake's typed loader failed on, in words: the YAML error, a missing
    scenario, an unknown field (where it is), fields left without a value; and a hint when the file looks cut short."""
    import yaml

    where = f"cannot load scenario '{scenario_name}' from {filename}"
    text = filename.read_text(errors="replace")
    cut_short = "" if text.endswith("\n") or not text else " (the file does not end with a line break: is it cut short?)"
    if isinstance(error, yaml.YAMLError):
        return f"{where}: not valid YAML: {error}{cut_short}"
    try:
        document = yaml.load(text, Loader=_AnyTagLoader)  # noqa: S506 (a SafeLoader that keeps tagged nodes as data)
    except yaml.YAMLError:
        document = None
    if not isinstance(document, dict):
        return f"{where}: the file holds no scenarios (it is empty or not a mapping of scenario names){cut_short}"
    if scenario_name not in document:
        return f"{where}: the file has no scenario '{scenario_name}'; it has {', '.join(map(str, document))}{cut_short}"
    body = document[scenario_name]
    if not isinstance(body, dict):
        return f"{where}: the scenario is {'empty' if body is None else 'not a mapping of fields'}{cut_short}"
    empty = _paths_of_key(body, None)
    if isinstance(error, AssertionError) and error.args and isinstance(error.args[0], str):  # Drake: unknown field
        paths = _paths_of_key(body, error.args[0])
        detail = f"unknown field '{error.args[0]}'" + (f" at {paths[0]}" if paths else "")
    elif empty:  # Drake's loader says e.g. "'NoneType' object is not iterable"
        detail = f"these fields have no value: {', '.join(empty[:5])}"
    else:
        detail = str(error)
    return f"{where}: {detail}{cut_short}"


def _paths_of_key(node, key: str | None, path: str = "") -> list[str]:
    """Where `node` (parsed YAML) has a field named `key`, as dotted paths; with `key` None, the fields whose value is
    empty (null)."""
    found: list[str] = []
    if isinstance(node, dict):
        for name, value in node.items():
            here = f"{path}.{name}" if path else str(name)
            if (key is None and value is None) or (key is not None and name == key):
                found.append(here)
            found += _paths_of_key(value, key, here)
    elif isinstance(node, list):
        for index, value in enumerate(node):
            found += _paths_of_key(value, key, f"{path}[{index}]")
    return found


def _any_tag_loader():
    """A YAML SafeLoader that reads Drake's tagged nodes (`!FovDegrees {...}`) as plain data."""
    import yaml

    class AnyTagLoader(yaml.SafeLoader):
        pass

    def untagged(loader, suffix, node):
        if isinstance(node, yaml.MappingNode):
            return loader.construct_mapping(node)
        if isinstance(node, yaml.SequenceNode):
            return loader.construct_sequence(node)
        return loader.construct_scalar(node)

    AnyTagLoader.add_multi_constructor("!", untagged)
    return AnyTagLoader


_AnyTagLoader = _any_tag_loader()


def _with_field(config, name: str, value):
    """A copy of the Drake config `config` with its field `name` set to `value`."""
    import copy

    config = copy.deepcopy(config)
    setattr(config, name, value)
    return config


def check_plant_config(config: MultibodyPlantConfig, field: str) -> None:
    """ScenarioError naming `field` and the accepted values when Drake refuses `config` (e.g. an unknown
    contact_model), found by making a plant of it now, before any station or simulation is built."""
    from pydrake.multibody.plant import AddMultibodyPlant, ContactModel, DiscreteContactApproximation
    from pydrake.systems.framework import DiagramBuilder

    def refusal(candidate: MultibodyPlantConfig) -> str | None:
        try:
            AddMultibodyPlant(candidate, DiagramBuilder())
        except Exception as error:  # noqa: BLE001 (Drake's RuntimeError names the field)
            return str(error)
        return None

    if not (math.isfinite(config.time_step) and config.time_step >= 0):
        return  # Drake would abort the process making this plant; make_station refuses the time step, naming it
    problem = refusal(config)
    if problem is None:
        return
    for name, enum in (("contact_model", ContactModel), ("discrete_contact_approximation", DiscreteContactApproximation)):
        if name in problem:
            # Drake's names are its enum's members in snake case; keep those it accepts here.
            names = [re.sub(r"(?<!^)(?=[A-Z])", "_", member[1:]).lower() for member in enum.__members__]
            drake_log = logging.getLogger("drake")
            level = drake_log.level
            drake_log.setLevel(logging.ERROR)  # not the deprecation warnings of the names tried
            try:
                accepted = [n for n in names if refusal(_with_field(config, name, n)) is None]
            finally:
                drake_log.setLevel(level)
            raise ScenarioError(f"{field}.{name} must be one of {', '.join(accepted)}; got {getattr(config, name)!r}")
    raise ScenarioError(f"{field}: {problem}")


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
