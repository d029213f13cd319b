"""An exponential moving average of the trained weights (TrainConfig.ema_decay), as diffusion and
flow-matching policies are usually evaluated (Diffusion Policy, Chi et al. 2023): the average of the
last ~1/(1 - decay) steps' weights is smoother than the last step's.

The decay ramps up as min(decay, (1 + n) / (10 + n)) after n updates, so a run's first steps do not
leave its starting weights in the average for long. `swapped_in` puts the average into the model
(for writing a checkpoint) and restores the trained weights afterwards.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import nn


def ramped_decay(decay: float, updates: int) -> float:
    """The decay of the update after `updates` earlier ones."""
    return min(decay, (1.0 + updates) / (10.0 + updates))


class WeightAverage:
    """The moving average of `module`'s parameters that require a gradient."""

    def __init__(self, module: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"ema_decay must be in (0, 1); got {decay}")
        self.decay = float(decay)
        self.params = {name: p for name, p in module.named_parameters() if p.requires_grad}
        if not self.params:
            raise ValueError("the weight average has no trained parameters to average")
        self.average = {name: p.detach().clone() for name, p in self.params.items()}
        self.updates = 0

    @torch.no_grad()
    def update(self) -> None:
        """Moves the average towards the current weights (call after each optimizer step)."""
        d = ramped_decay(self.decay, self.updates)
        for name, p in self.params.items():
            self.average[name].mul_(d).add_(p.detach(), alpha=1.0 - d)
        self.updates += 1

    def state_dict(self) -> dict:
        """The average, the trained weights and the update count (for a resumable checkpoint)."""
        return {  # the decay is the run's train_config.yaml's, which a resume may not change
            "updates": self.updates,
            "average": {k: v.detach().cpu().clone() for k, v in self.average.items()},
            "trained": {k: p.detach().cpu().clone() for k, p in self.params.items()},
        }

    @torch.no_grad()
    def load_state_dict(self, state: dict) -> None:
        """Restores the average and puts the trained weights back into the parameters."""
        names = set(self.params)
        missing = (names - set(state.get("average", {}))) | (names - set(state.get("trained", {})))
        if missing:
            raise ValueError(f"the checkpoint's weight average lacks {sorted(missing)[:3]} "
                             f"({len(missing)} parameters)")
        for name, p in self.params.items():
            self.average[name].copy_(state["average"][name])
            p.copy_(state["trained"][name])
        self.updates = int(state["updates"])

    @contextlib.contextmanager
    def swapped_in(self) -> Iterator[None]:
        """Within the block the parameters hold the average; afterwards the trained weights again."""
        with torch.no_grad():
            trained = {name: p.detach().clone() for name, p in self.params.items()}
            for name, p in self.params.items():
                p.copy_(self.average[name])
        try:
            yield
        finally:
            with torch.no_grad():
                for name, p in self.params.items():
                    p.copy_(trained[name])
