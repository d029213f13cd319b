"""Multi-head attention (self or cross) on torch's scaled_dot_product_attention, with a key padding mask."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class MultiHeadAttention(nn.Module):
    """Multi-head attention of queries (B, Nq, D) over keys/values (B, Nk, Dkv); `key_mask` (B, Nk) is True
    for keys that may be attended to."""

    def __init__(self, dim: int, num_heads: int, kv_dim: int | None = None) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"attention width {dim} is not divisible by {num_heads} heads")
        kv_dim = kv_dim or dim
        self.num_heads = num_heads
        self.to_q = nn.Linear(dim, dim)
        self.to_k = nn.Linear(kv_dim, dim)
        self.to_v = nn.Linear(kv_dim, dim)
        self.to_out = nn.Linear(dim, dim)

    def forward(
        self, x: torch.Tensor, context: torch.Tensor | None = None, key_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Attends x to `context` (x itself when None)."""
        context = x if context is None else context
        batch, nq, dim = x.shape
        h = self.num_heads
        q = self.to_q(x).view(batch, nq, h, -1).transpose(1, 2)
        k = self.to_k(context).view(batch, context.shape[1], h, -1).transpose(1, 2)
        v = self.to_v(context).view(batch, context.shape[1], h, -1).transpose(1, 2)
        attn_mask = None if key_mask is None else key_mask[:, None, None, :]
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)
        return self.to_out(out.transpose(1, 2).reshape(batch, nq, dim))


class FeedForward(nn.Module):
    """Two-layer GELU MLP."""

    def __init__(self, dim: int, ratio: float = 4.0) -> None:
        super().__init__()
        hidden = int(dim * ratio)
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(approximate="tanh"), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Applies the MLP token-wise."""
        return self.net(x)
