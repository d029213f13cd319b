"""The diffusion transformer (DiT) of System 1's action head.

Tokens are [Q_s; action tokens]. Each block: adaptive-LayerNorm (the flow time) self-attention over
the tokens, cross-attention to the condition tokens (Q_vl and Q_p), adaptive-LayerNorm FFN.
AdaLN-Zero: the modulation is zero-initialised so every block starts as the identity.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from trivla_drake.nn.attention import FeedForward, MultiHeadAttention


def sinusoidal_embedding(t: torch.Tensor, dim: int, scale: float = 1000.0) -> torch.Tensor:
    """Sinusoidal features (B, dim) of times t (B,) in [0, 1] (scaled to [0, `scale`], as DDPM steps)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = (t.float() * scale)[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.nn.functional.pad(emb, (0, 1))
    return emb


class TimeEmbedding(nn.Module):
    """Flow time t (B,) -> conditioning vector (B, dim): sinusoidal features then an MLP."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.mlp = nn.Sequential(nn.Linear(dim, dim), nn.SiLU(), nn.Linear(dim, dim))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        """Embeds the times."""
        return self.mlp(sinusoidal_embedding(t, self.dim).to(self.mlp[0].weight.dtype))


def _modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1.0 + scale.unsqueeze(1)) + shift.unsqueeze(1)


class DiTBlock(nn.Module):
    """AdaLN-Zero self-attention, cross-attention to the condition tokens, AdaLN-Zero FFN."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.norm_self = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.self_attn = MultiHeadAttention(dim, num_heads)
        self.norm_cross = nn.LayerNorm(dim, eps=1e-6)
        self.cross_attn = MultiHeadAttention(dim, num_heads)
        self.norm_ffn = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.ffn = FeedForward(dim, mlp_ratio)
        self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim, 6 * dim))
        nn.init.zeros_(self.modulation[1].weight)
        nn.init.zeros_(self.modulation[1].bias)

    def forward(
        self, x: torch.Tensor, cond: torch.Tensor, memory: torch.Tensor, memory_mask: torch.Tensor | None
    ) -> torch.Tensor:
        """x (B, N, D) tokens, cond (B, D) time embedding, memory (B, M, D) condition tokens."""
        shift1, scale1, gate1, shift2, scale2, gate2 = self.modulation(cond).chunk(6, dim=-1)
        x = x + gate1.unsqueeze(1) * self.self_attn(_modulate(self.norm_self(x), shift1, scale1))
        x = x + self.cross_attn(self.norm_cross(x), memory, memory_mask)
        x = x + gate2.unsqueeze(1) * self.ffn(_modulate(self.norm_ffn(x), shift2, scale2))
        return x


class DiffusionTransformer(nn.Module):
    """A stack of DiT blocks and a final adaptive LayerNorm."""

    def __init__(self, dim: int, depth: int, num_heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.blocks = nn.ModuleList([DiTBlock(dim, num_heads, mlp_ratio) for _ in range(depth)])
        self.norm_out = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.modulation_out = nn.Sequential(nn.SiLU(), nn.Linear(dim, 2 * dim))
        nn.init.zeros_(self.modulation_out[1].weight)
        nn.init.zeros_(self.modulation_out[1].bias)

    def forward(
        self, x: torch.Tensor, cond: torch.Tensor, memory: torch.Tensor, memory_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Runs the blocks; returns tokens (B, N, D)."""
        for block in self.blocks:
            x = block(x, cond, memory, memory_mask)
        shift, scale = self.modulation_out(cond).chunk(2, dim=-1)
        return _modulate(self.norm_out(x), shift, scale)
