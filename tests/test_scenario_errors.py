"""A bad scenario file fails with an error naming the file and the field."""

from __future__ import annotations

import pytest

from trivla_drake.station.scenario import ScenarioError, default_scenario_file, load_scenario
from trivla_drake.station.station import make_station


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ScenarioError, match="nope.yaml"):
        load_scenario(tmp_path / "nope.yaml")


def test_unparsable_yaml_names_the_file(tmp_path):
    bad = tmp_path / "bad.scenarios.yaml"
    bad.write_text("default:\n  plant_config: [unclosed\n")
    with pytest.raises(ScenarioError, match="bad.scenarios.yaml"):
        load_scenario(bad)


def test_unknown_field_is_named(tmp_path):
    bad = tmp_path / "typo.scenarios.yaml"
    bad.write_text("default:\n  plant_config:\n    time_stepp: 0.01\n")
    with pytest.raises(ScenarioError, match="time_stepp"):
        load_scenario(bad)


def test_unknown_scenario_name_is_named():
    with pytest.raises(ScenarioError, match="no_such_scenario"):
        load_scenario(default_scenario_file(), "no_such_scenario")


def test_unknown_model_file_names_the_directive(tmp_path):
    text = default_scenario_file().read_text().replace("block_green.sdf", "block_purple.sdf")
    bad = tmp_path / "unknown_model.scenarios.yaml"
    bad.write_text(text)
    scenario = load_scenario(bad)
    with pytest.raises(ScenarioError, match=r"directives\[\d+\]\.add_model \(name 'block_green'\).*block_purple"):
        make_station(scenario)


def test_scenario_without_a_panda_is_rejected(scenario):
    scenario.directives = [d for d in scenario.directives if not (d.add_model and d.add_model.name == "panda")]
    scenario.directives = [d for d in scenario.directives if not (d.add_weld and "panda" in d.add_weld.child)]
    with pytest.raises(ScenarioError, match="panda"):
        make_station(scenario)


def test_camera_on_unknown_frame_is_named(scenario):
    scenario.cameras["wrist_camera"].X_PB.base_frame = "panda::no_such_link"
    with pytest.raises(ValueError, match="cameras.wrist_camera.X_PB.base_frame"):
        make_station(scenario)
