"""The policy-wrapper registry: wrappers around a `Policy` (reset / act) that change how it is run, applied by
name (`EvalConfig.policy_wrappers`, `wrap_policy`).

    @register_policy_wrapper("name")
    def make_mine(policy) -> Policy: ...

Registered here: "home_first" (eval/home_first.py, `evaluate --home-first`)."""

from __future__ import annotations

from collections.abc import Sequence

from trivla_drake.eval.registry import Registry

POLICY_WRAPPERS = Registry("policy wrapper")


def register_policy_wrapper(name: str):
    """A decorator registering a factory `factory(policy) -> Policy` under `name`."""
    return POLICY_WRAPPERS.register(name)


def check_policy_wrappers(names: Sequence[str]) -> None:
    """ValueError naming the registered wrappers if one of `names` is not registered."""
    for name in names:
        POLICY_WRAPPERS.check(name)


def wrap_policy(policy, names: Sequence[str]):
    """`policy` inside the wrappers `names`, the first innermost; ValueError for an unknown name."""
    for name in names:
        policy = POLICY_WRAPPERS.make(name, policy)
    return policy


@register_policy_wrapper("home_first")
def home_first(policy):
    """`HomeFirst(policy)`: later tasks start after a scripted homing (eval/home_first.py)."""
    from trivla_drake.eval.home_first import HomeFirst

    return HomeFirst(policy)
