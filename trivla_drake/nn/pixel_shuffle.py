"""Pixel shuffle (space-to-depth) of a ViT patch grid, as Eagle-2 / InternVL use to cut image tokens 4x."""

from __future__ import annotations

import torch


def pixel_shuffle(tokens: torch.Tensor, ratio: float = 0.5) -> torch.Tensor:
    """Folds each k x k block of a square token grid into one token with k^2 x the channels (k = 1/ratio).

    tokens: (B, N, C) with N = G^2 patches in row-major order. Returns (B, N / k^2, C k^2) where output
    token (i, j) is the concatenation of input tokens (k i + r, k j + c) in row-major (r, c) order, the
    channel layout of Eagle-2's pixel shuffle (ps_version v2), so its projector weights apply unchanged.
    """
    batch, num, channels = tokens.shape
    k = round(1 / ratio)
    grid = round(num**0.5)
    if grid * grid != num or grid % k:
        raise ValueError(f"pixel_shuffle needs a square grid divisible by {k}; got {num} tokens")
    g = grid // k
    x = tokens.reshape(batch, g, k, g, k, channels)  # (B, i, r, j, c, C)
    x = x.permute(0, 1, 3, 2, 4, 5)  # (B, i, j, r, c, C)
    return x.reshape(batch, g * g, k * k * channels)
