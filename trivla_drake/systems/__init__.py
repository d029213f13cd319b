"""trivla_drake.systems: Drake LeafSystems, thin adapters over nn/ and robot/."""

from trivla_drake.systems.diffik_system import DifferentialIKSystem

__all__ = ["DifferentialIKSystem"]
