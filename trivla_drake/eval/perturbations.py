"""The perturbation registry: disturbances of the applied actions that `run_episode(perturbation=...)` runs (the
recorded actions stay the policy's; eval/action_noise.py has the `Disturbance` interface).

    @register_perturbation("name")
    def make_mine(**settings) -> Disturbance: ...

    run_episode(task, seed, policy, perturbation=make_perturbation("dart", scale=1.0))

Registered here: "dart", DART's perturbation bursts (`collect --set perturbation.name=dart`)."""

from __future__ import annotations

from trivla_drake.eval.action_noise import Disturbance, PerturbationBursts
from trivla_drake.eval.registry import Registry

PERTURBATIONS = Registry("perturbation")


def register_perturbation(name: str):
    """A decorator registering a factory of a `Disturbance` under `name`."""
    return PERTURBATIONS.register(name)


def make_perturbation(name: str, **settings) -> Disturbance:
    """The perturbation registered as `name`, made with `settings`; ValueError naming the registered ones."""
    return PERTURBATIONS.make(name, **settings)


@register_perturbation("dart")
def dart(scale: float = 1.0) -> PerturbationBursts:
    """DART's perturbation bursts at `scale` times the default burst rate (`collect --set perturbation.name=dart`)."""
    return PerturbationBursts.scaled(scale)
