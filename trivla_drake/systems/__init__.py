"""trivla_drake.systems: Drake LeafSystems, thin adapters over nn/ and robot/ (the public API is exported by
`trivla_drake` itself: `from trivla_drake import TriVLAPolicy, add_trivla_policy, ...`)."""

from trivla_drake.systems.diffik_system import DifferentialIKSystem

__all__ = ["DifferentialIKSystem"]
