"""Standardisation of the frozen System 2/3 features System 1 reads, with training-set statistics.

What changes from scene to scene in the frozen features is a small part of them: in our cached
features the variance across demonstrations is about 0.3% of the mean square of System 2's image
tokens and 0.1% of System 3's features; the rest is the same in every scene (the layout of the
prompt, the table, the robot). Read raw, System 1 learns to ignore them (its actions did not change
when the static camera showed another scene). Subtracting the training-set mean of each element and
dividing by its standard deviation (lerobot's MEAN_STD mode, applied to features) puts the
scene-dependent part at unit scale.

The statistics are buffers of System 1 (saved with its weights); until `fit` is called they are the
identity (mean 0, std 1).
"""

from __future__ import annotations

import torch
from torch import nn

STD_FLOOR_FRACTION = 0.1  # stds are floored at this fraction of their mean, so near-constant elements stay tame


class FeatureStandardizer(nn.Module):
    """(x - mean) / std over the trailing dimensions `shape` of its input."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__()
        self.shape = tuple(shape)
        self.register_buffer("mean", torch.zeros(self.shape))
        self.register_buffer("std", torch.ones(self.shape))

    def fit(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Sets the statistics (each of `shape`); stds are floored at STD_FLOOR_FRACTION of their mean."""
        for name, value in (("mean", mean), ("std", std)):
            if tuple(value.shape) != self.shape:
                raise ValueError(f"feature {name} must have shape {self.shape}; got {tuple(value.shape)}")
            if not torch.isfinite(value).all():
                raise ValueError(f"feature {name} has non-finite values")
        std = std.to(torch.float32)
        floor = STD_FLOOR_FRACTION * float(std.mean()) + 1e-12
        self.mean.copy_(mean.to(self.mean.dtype))
        self.std.copy_(std.clamp_min(floor).to(self.std.dtype))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Standardises x (..., *shape)."""
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)


class SequenceStandardizer(FeatureStandardizer):
    """Standardisation of token sequences (B, S, D) whose first `positions` tokens have a fixed role
    (System 2's prompt head and image tokens): each of those positions has its own statistics, and
    all later tokens (the instruction) share one more row."""

    def __init__(self, positions: int, dim: int) -> None:
        super().__init__((positions + 1, dim))
        self.positions = positions

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Standardises x (B, S, D) position by position."""
        index = torch.arange(x.shape[1], device=x.device).clamp_max(self.positions)
        return (x - self.mean[index].to(x.dtype)) / self.std[index].to(x.dtype)


class MomentAccumulator:
    """Running per-element sums (float64) of samples of one shape, for the statistics above."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.sum = torch.zeros(shape, dtype=torch.float64)
        self.sum_sq = torch.zeros(shape, dtype=torch.float64)
        self.count = torch.zeros(shape[:1] + (1,) * (len(shape) - 1), dtype=torch.float64)

    def add(self, x: torch.Tensor, rows: slice | None = None) -> None:
        """Adds samples x (N, *shape) -- or, with `rows`, samples of the leading rows `rows` only."""
        x = x.to(torch.float64)
        target = slice(None) if rows is None else rows
        self.sum[target] += x.sum(0)
        self.sum_sq[target] += (x * x).sum(0)
        self.count[target] += x.shape[0]

    def mean_std(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and standard deviation; ValueError if some element saw no sample."""
        if (self.count == 0).any():
            raise ValueError("no samples for some feature elements: cannot compute their statistics")
        mean = self.sum / self.count
        var = (self.sum_sq / self.count - mean * mean).clamp_min(0.0)
        return mean.float(), var.sqrt().float()
