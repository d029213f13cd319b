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


def _move_panda_base(scenario):
    import pydrake.common.schema as schema

    for directive in scenario.directives:
        if directive.add_weld and directive.add_weld.child == "panda::panda_link0":
            moved = schema.Transform()
            moved.translation = [0.0, 0.2, 0.0]
            directive.add_weld.X_PC = moved
            return
    raise AssertionError("the default scenario welds panda::panda_link0")


@pytest.mark.parametrize("mutate, field", [
    (lambda s: setattr(s.cameras["static_camera"], "fps", float("nan")), "cameras.static_camera.fps"),
    (lambda s: setattr(s.cameras["static_camera"], "fps", float("inf")), "cameras.static_camera.fps"),
    (lambda s: setattr(s.cameras["static_camera"], "width", 0), "cameras.static_camera.width"),
    (lambda s: setattr(s.cameras["wrist_camera"], "depth", True), "cameras.wrist_camera.depth"),
    (lambda s: setattr(s.cameras["wrist_camera"], "capture_offset", 0.05), "cameras.wrist_camera.capture_offset"),
    (lambda s: setattr(s.cameras["wrist_camera"], "output_delay", 0.1), "cameras.wrist_camera.output_delay"),
    (lambda s: setattr(s.cameras["wrist_camera"], "renderer_class", "RenderEngineGl"),
     "cameras.wrist_camera.renderer_class"),
    (lambda s: s.panda_driver.arm_kp.__setitem__(3, -1.0), r"panda_driver.arm_kp\[3\]"),
    (lambda s: setattr(s.panda_driver, "finger_kd", float("inf")), "panda_driver.finger_kd"),
    (lambda s: setattr(s.plant_config, "time_step", -0.01), "plant_config.time_step"),
    (_move_panda_base, "panda_link0 must be welded at the world origin"),
])
def test_values_the_station_cannot_honour_are_named(scenario, mutate, field):
    """Each of these used to be ignored, give a wrong hand pose (a moved base) or abort the whole process (a
    negative gain or time step)."""
    mutate(scenario)
    with pytest.raises(ValueError, match=field):
        make_station(scenario)


def test_camera_background_other_than_the_renderers_is_named(scenario):
    from pydrake.geometry import Rgba

    scenario.cameras["static_camera"].background = Rgba(0.2, 0.2, 0.2, 1.0)
    with pytest.raises(ValueError, match="cameras.static_camera.background"):
        make_station(scenario)


def test_unknown_contact_model_names_the_field_and_the_accepted_values(tmp_path):
    bad = tmp_path / "typo.scenarios.yaml"
    bad.write_text(default_scenario_file().read_text().replace("lagged", "lagd"))
    with pytest.raises(ScenarioError, match=r"typo.scenarios.yaml: plant_config.discrete_contact_approximation must be "
                                            r"one of tamsi, sap, similar, lagged; got 'lagd'"):
        load_scenario(bad)


@pytest.mark.parametrize("cut_after, message", [
    ("  directives:\n", r"these fields have no value: directives \(the file does not end"),
    ("      default_joint_positions:\n", r"these fields have no value: directives\[2\]\.add_model\.default_joint_positions"),
    ("  plant_config:\n    tim", r"unknown field 'tim' \(the file does not end with a line break: is it cut short\?\)"),
    ("default", r"the file holds no scenarios"),
])
def test_a_truncated_file_says_what_is_missing_and_that_it_looks_cut_short(tmp_path, cut_after, message):
    text = default_scenario_file().read_text()
    cut = tmp_path / "cut.scenarios.yaml"
    cut.write_text(text[:text.index(cut_after) + len(cut_after)].rstrip("\n") + " ")
    with pytest.raises(ScenarioError, match=r"cannot load scenario 'default' from .*cut.scenarios.yaml: " + message):
        load_scenario(cut)
