"""Normalisation statistics the model carries: states are standardised (mean/std) and actions are
min-max scaled to [-1, 1] (lerobot's MEAN_STD / MIN_MAX modes, with an epsilon guard)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

EPS = 1e-8
# The smallest state standard deviation normalize_state divides by (rad, m, rad/s or m/s).
STATE_STD_FLOOR = 1e-3
_FIELDS = ("state_mean", "state_std", "action_min", "action_max")


@dataclass
class NormalizationStats:
    """Per-dimension statistics of states and actions (plain lists, JSON-able)."""

    state_mean: list[float]
    state_std: list[float]
    action_min: list[float]
    action_max: list[float]

    @classmethod
    def identity(cls, state_dim: int, action_dim: int) -> "NormalizationStats":
        """Statistics that leave states unchanged and map actions in [-1, 1] to themselves."""
        return cls([0.0] * state_dim, [1.0] * state_dim, [-1.0] * action_dim, [1.0] * action_dim)

    @classmethod
    def from_data(cls, states: np.ndarray, actions: np.ndarray) -> "NormalizationStats":
        """Statistics of states (N, state_dim) and actions (N, ..., action_dim)."""
        states = np.asarray(states, dtype=np.float64).reshape(-1, np.shape(states)[-1])
        actions = np.asarray(actions, dtype=np.float64).reshape(-1, np.shape(actions)[-1])
        return cls(
            states.mean(0).tolist(), states.std(0).tolist(), actions.min(0).tolist(), actions.max(0).tolist()
        )

    def to_dict(self) -> dict[str, list[float]]:
        """JSON-able form."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "NormalizationStats":
        """Inverse of `to_dict`; raises ValueError on missing or non-finite entries."""
        try:
            stats = cls(**{k: [float(v) for v in data[k]] for k in _FIELDS})
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"normalization statistics are malformed: {exc}") from exc
        for name, values in asdict(stats).items():
            if not np.all(np.isfinite(values)):
                raise ValueError(f"normalization.{name} has non-finite values")
        return stats

    def check_dims(self, state_dim: int, action_dim: int) -> None:
        """Raises ValueError naming the field whose length is wrong."""
        for name in _FIELDS:
            n = state_dim if name.startswith("state") else action_dim
            if len(getattr(self, name)) != n:
                raise ValueError(f"normalization.{name} has {len(getattr(self, name))} values; expected {n}")


class Normalizer(nn.Module):
    """Applies NormalizationStats to tensors (statistics are buffers, not trained, saved in config.json)."""

    def __init__(self, stats: NormalizationStats) -> None:
        super().__init__()
        self.register_buffer("state_mean", torch.zeros(0), persistent=False)
        self.register_buffer("state_std", torch.ones(0), persistent=False)
        self.register_buffer("action_min", torch.zeros(0), persistent=False)
        self.register_buffer("action_max", torch.ones(0), persistent=False)
        self.set_stats(stats)

    def set_stats(self, stats: NormalizationStats) -> None:
        """Replaces the statistics."""
        self.stats = stats
        device = self.state_mean.device
        for name, values in asdict(stats).items():
            setattr(self, name, torch.tensor(values, dtype=torch.float32, device=device))

    def normalize_state(self, state: torch.Tensor) -> torch.Tensor:
        """(state - mean) / std, the std floored at STATE_STD_FLOOR: a dimension constant in the data (an
        unused joint) is not multiplied by 1e8 at test time. The shipped statistics' smallest std is 0.015."""
        # + EPS as before the floor: for every std above it the result is bit-identical to earlier releases'.
        return (state - self.state_mean) / (self.state_std.clamp_min(STATE_STD_FLOOR) + EPS)

    def normalize_action(self, action: torch.Tensor) -> torch.Tensor:
        """Maps [min, max] to [-1, 1]."""
        return 2.0 * (action - self.action_min) / (self.action_max - self.action_min + EPS) - 1.0

    def unnormalize_action(self, action: torch.Tensor) -> torch.Tensor:
        """Maps [-1, 1] back to [min, max]."""
        return (action + 1.0) * 0.5 * (self.action_max - self.action_min + EPS) + self.action_min
