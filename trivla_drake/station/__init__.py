"""trivla_drake.station: scenario -> plant, cameras, driver, Meshcat."""

from trivla_drake.station.scenario import Scenario, ScenarioError, load_scenario, make_simulator
from trivla_drake.station.station import make_station

__all__ = ["Scenario", "ScenarioError", "load_scenario", "make_simulator", "make_station"]
