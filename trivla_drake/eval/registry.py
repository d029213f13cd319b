"""`Registry`: named factories of one kind of plug-in (the perturbations of eval/perturbations.py, the policy
wrappers of eval/policy_wrappers.py), registered by name and made by name, in the spirit of lerobot's
`register_subclass`. A variation of how episodes run is one registered factory, not one more keyword."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


class Registry:
    """Factories of one `kind` of plug-in by name: `@registry.register(name)` adds one, `make(name, ...)` calls it."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._factories: dict[str, Callable[..., Any]] = {}

    def register(self, name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        """A decorator registering its factory under `name`; ValueError if `name` is taken."""
        def add(factory: Callable[..., Any]) -> Callable[..., Any]:
            if name in self._factories:
                raise ValueError(f"a {self.kind} named {name!r} is registered already")
            self._factories[name] = factory
            return factory

        return add

    def names(self) -> list[str]:
        """The registered names, sorted."""
        return sorted(self._factories)

    def check(self, name: str) -> str:
        """`name` if registered; else ValueError naming the registered ones."""
        if name not in self._factories:
            raise ValueError(f"unknown {self.kind} {name!r}; registered: {', '.join(self.names()) or 'none'}")
        return name

    def make(self, name: str, *args: Any, **settings: Any) -> Any:
        """What the factory registered as `name` makes of `args` and `settings` (an unknown name: see `check`)."""
        return self._factories[self.check(name)](*args, **settings)
