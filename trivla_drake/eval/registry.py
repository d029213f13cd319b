"""`Registry`: named factories of one kind of plug-in (the perturbations of eval/perturbations.py, the policy
wrappers of eval/policy_wrappers.py), registered by name and made by name, in the spirit of lerobot's
`register_subclass`. A variation of how episodes run is one registered factory, not one more keyword."""

from __future__ import annotations

import inspect
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
        """What the factory registered as `name` makes of `args` and `settings` (an unknown name: see `check`).
        ValueError naming the kind, `name` and the setting if the factory does not take `settings` (an unknown or
        a missing one); errors raised by the factory itself pass through unchanged."""
        factory = self._factories[self.check(name)]
        try:
            signature = inspect.signature(factory)
        except (TypeError, ValueError):  # no signature to check against (a builtin): the factory's own errors
            signature = None
        if signature is not None:
            try:
                signature.bind(*args, **settings)
            except TypeError as error:
                parameters = signature.parameters.values()
                takes = [p.name for p in parameters if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
                unknown = [key for key in settings if key not in takes]
                if unknown and not any(p.kind is p.VAR_KEYWORD for p in parameters):  # named first, as Python does
                    error = f"unknown setting(s) {', '.join(map(repr, unknown))}; it takes {', '.join(takes) or 'none'}"
                raise ValueError(f"settings of the {self.kind} {name!r}: {error}") from None
        return factory(*args, **settings)
