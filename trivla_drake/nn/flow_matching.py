"""Flow matching for System 1's action chunks (GR00T N1's convention).

Time convention: t in [0, 1], t = 0 is pure noise and t = 1 is the data (the action chunk).
    x_t = (1 - t) * noise + t * action,       target velocity  v = dx_t/dt = action - noise.
Training samples t = (s - u) / s with u ~ Beta(alpha, beta) (alpha = 1.5, beta = 1, s = 0.999), which
puts more weight on the noisy end. Inference integrates dx/dt = v(x, t) with Euler steps from
t = 0 (x ~ N(0, I)) to t = 1. (lerobot's pi0/smolvla run the opposite direction, 1 = noise.)
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F


def sample_flow_time(
    batch: int,
    *,
    alpha: float = 1.5,
    beta: float = 1.0,
    s: float = 0.999,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Training times t (B,) in [0, 1]: t = (s - u) / s, u ~ Beta(alpha, beta), clipped to [0, 1]."""
    if beta == 1.0:
        u = torch.rand(batch, generator=generator) ** (1.0 / alpha)  # inverse CDF of Beta(alpha, 1)
    elif alpha == 1.0:
        u = 1.0 - torch.rand(batch, generator=generator) ** (1.0 / beta)  # inverse CDF of Beta(1, beta)
    else:  # general case through numpy, seeded from the torch generator so it stays reproducible
        seed = int(torch.randint(0, 2**62, (1,), generator=generator))
        u = torch.from_numpy(np.random.default_rng(seed).beta(alpha, beta, size=batch)).float()
    return ((s - u) / s).clamp(0.0, 1.0)


def interpolate(noise: torch.Tensor, data: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x_t = (1 - t) noise + t data, t broadcast from (B,)."""
    t = t.view(-1, *([1] * (data.dim() - 1))).to(data.dtype)
    return (1.0 - t) * noise + t * data


def velocity_target(noise: torch.Tensor, data: torch.Tensor) -> torch.Tensor:
    """The constant velocity of the straight path from noise to data: data - noise."""
    return data - noise


def flow_matching_loss(
    velocity_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    data: torch.Tensor,
    *,
    alpha: float = 1.5,
    beta: float = 1.0,
    s: float = 0.999,
    generator: torch.Generator | None = None,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean squared velocity error || v(x_t, t) - (data - noise) ||^2 over a batch of data (B, ...).
    `mask` (broadcastable to data, True = counts) leaves out padded entries. Returns (loss, t)."""
    t = sample_flow_time(data.shape[0], alpha=alpha, beta=beta, s=s, generator=generator).to(data.device)
    noise = torch.randn(data.shape, generator=generator, dtype=torch.float32).to(data.device, data.dtype)
    x_t = interpolate(noise, data, t)
    error = F.mse_loss(velocity_fn(x_t, t), velocity_target(noise, data), reduction="none")
    if mask is None:
        return error.mean(), t
    weight = mask.to(error.dtype).expand_as(error)
    return (error * weight).sum() / weight.sum().clamp_min(1.0), t


def euler_sample(
    velocity_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    noise: torch.Tensor,
    num_steps: int,
) -> torch.Tensor:
    """Integrates dx/dt = v(x, t) from t = 0 (x = noise) to t = 1 with `num_steps` Euler steps."""
    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1; got {num_steps}")
    x = noise
    dt = 1.0 / num_steps
    for i in range(num_steps):
        t = torch.full((x.shape[0],), i * dt, dtype=x.dtype, device=x.device)
        x = x + dt * velocity_fn(x, t)
    return x
