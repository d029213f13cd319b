"""trivla-drake: the TriVLA vision-language-action policy as Drake systems.

The public API, importable from here (`from trivla_drake import TriVLAPolicy, add_trivla_policy`). Each name is
imported on first use, so `import trivla_drake` (and the CLI) works without Drake or torch installed.
"""

import importlib

__version__ = "0.1.0"

# Public name -> the module that defines it.
_PUBLIC = {
    # The policy as Drake systems (ports, frames and rates in each docstring).
    "TriVLAPolicy": "trivla_drake.systems.trivla_policy",
    "PolicyRates": "trivla_drake.systems.trivla_policy",
    "LatencyModel": "trivla_drake.systems.latency",
    "add_trivla_policy": "trivla_drake.systems.policy_wiring",
    "TriVLAPolicyConfig": "trivla_drake.systems.policy_config",
    "ApplyTriVLAPolicyConfig": "trivla_drake.systems.policy_config",
    "robot_base_pose": "trivla_drake.systems.robot_base",
    "DifferentialIKSystem": "trivla_drake.systems.diffik_system",
    "DiffIKParams": "trivla_drake.robot.osqp_diffik",
    # The model.
    "load_model": "trivla_drake.eval.model_loading",
    # The Panda for a plant of one's own: model file, parser, driver, cameras.
    "drake_panda_urdf": "trivla_drake.robot.panda_assets",
    "make_parser": "trivla_drake.station.station",
    "add_panda_driver": "trivla_drake.station.panda_driver",
    "make_panda_only_plant": "trivla_drake.station.panda_driver",
    "PandaDriverConfig": "trivla_drake.station.scenario",
    "add_rgb_camera": "trivla_drake.station.cameras",
    # The project's station.
    "make_station": "trivla_drake.station.station",
    "load_scenario": "trivla_drake.station.scenario",
    "make_simulator": "trivla_drake.station.scenario",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'trivla_drake' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
