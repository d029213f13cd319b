"""`PluginConfig`: a registered plug-in (a perturbation of eval/perturbations.py, a policy wrapper of
eval/policy_wrappers.py) named in a job's config, with the keyword settings of its factory:

    perturbation: {name: dart, settings: {scale: 1.0}}
    policy_wrappers: [{name: home_first}]
"""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc


@dc.dataclass
class PluginConfig:
    """One registered plug-in by name, with its factory's keyword settings."""

    # The registered name ("" in an optional slot: none).
    name: str = ""
    # Keyword settings of its factory, e.g. {scale: 1.0} for the perturbation "dart" (empty: the factory's defaults).
    settings: dict[str, float] = dc.field(default_factory=dict)

    def key(self) -> tuple:
        """A hashable form (name, sorted settings), e.g. to cache what it makes."""
        return self.name, tuple(sorted(self.settings.items()))
