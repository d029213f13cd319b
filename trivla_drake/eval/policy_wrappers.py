"""The policy-wrapper registry: wrappers around a `Policy` (reset / act) that change how it is run, named with their
settings in a config (`EvalConfig.policy_wrappers`, a list of PluginConfig) and applied by `wrap_policy`.

    @register_policy_wrapper("name")
    def make_mine(policy, **settings) -> Policy: ...

Registered here: "home_first" (eval/home_first.py; `evaluate --set 'policy_wrappers=[{name: home_first}]'`)."""

from __future__ import annotations

from collections.abc import Sequence

from trivla_drake.eval.plugin_config import PluginConfig
from trivla_drake.eval.registry import Registry

POLICY_WRAPPERS = Registry("policy wrapper")


def register_policy_wrapper(name: str):
    """A decorator registering a factory `factory(policy, **settings) -> Policy` under `name`."""
    return POLICY_WRAPPERS.register(name)


def check_policy_wrappers(wrappers: Sequence[PluginConfig], field: str = "policy_wrappers") -> None:
    """ValueError naming `field` and the registered wrappers if one of `wrappers` is not registered."""
    for index, wrapper in enumerate(wrappers):
        try:
            POLICY_WRAPPERS.check(wrapper.name)
        except ValueError as error:
            raise ValueError(f"{field}[{index}].name: {error}") from None


def wrap_policy(policy, wrappers: Sequence[PluginConfig]):
    """`policy` inside `wrappers` (each made with its settings), the first innermost; ValueError for an unknown
    name or a setting its wrapper does not take."""
    for wrapper in wrappers:
        policy = POLICY_WRAPPERS.make(wrapper.name, policy, **wrapper.settings)
    return policy


@register_policy_wrapper("home_first")
def home_first(policy):
    """`HomeFirst(policy)`: later tasks start after a scripted homing (eval/home_first.py)."""
    from trivla_drake.eval.home_first import HomeFirst

    return HomeFirst(policy)
