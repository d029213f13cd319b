"""Noise levels of System 3's video diffusion, in SVD's convention (EDM sigmas, v-prediction).

A noised clip is x_sigma = x_0 + sigma * eps. This is the paper's eq. (1) form
x_t = sqrt(abar) x_0 + sqrt(1 - abar) eps up to the scale c_in(sigma) = sqrt(abar), with
abar = 1 / (1 + sigma^2): the UNet sees c_in * x_sigma and the time c_noise(sigma) = ln(sigma) / 4,
and its output F gives the x_0 estimate D = c_skip x_sigma + c_out F (what eq. (1) regresses on x_0).
Keeping SVD's convention means the released SVD weights work unchanged.
"""

from __future__ import annotations

import torch


def c_in(sigma: torch.Tensor) -> torch.Tensor:
    """Input scale 1 / sqrt(sigma^2 + 1) = sqrt(abar)."""
    return 1.0 / torch.sqrt(sigma**2 + 1.0)


def c_skip(sigma: torch.Tensor) -> torch.Tensor:
    """Skip weight of the x_0 estimate, 1 / (sigma^2 + 1)."""
    return 1.0 / (sigma**2 + 1.0)


def c_out(sigma: torch.Tensor) -> torch.Tensor:
    """Output weight of the x_0 estimate for v-prediction, -sigma / sqrt(sigma^2 + 1)."""
    return -sigma / torch.sqrt(sigma**2 + 1.0)


def c_noise(sigma: torch.Tensor) -> torch.Tensor:
    """The UNet's timestep input for noise level sigma, ln(sigma) / 4."""
    return 0.25 * torch.log(sigma)


def alpha_bar(sigma: torch.Tensor) -> torch.Tensor:
    """The DDPM cumulative signal rate of noise level sigma, 1 / (1 + sigma^2)."""
    return 1.0 / (1.0 + sigma**2)


def sample_training_sigmas(
    batch: int,
    log_mean: float,
    log_std: float,
    *,
    sigma_min: float,
    sigma_max: float,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Log-normal noise levels (B,) for training, clipped to [sigma_min, sigma_max]."""
    z = torch.randn(batch, generator=generator, device="cpu").to(device)
    sigma = torch.exp(log_mean + log_std * z)
    return sigma.clamp(sigma_min, sigma_max)

