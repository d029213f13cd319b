"""Eq. (4): compress the per-view predictive features F_p into T x L tokens Q_p.

Learnable queries Q[0:T, 0:L]; each layer does, per frame i, spatial attention of Q[i] over the
tokens of F_p^static[i] and F_p^wrist[i] together, then temporal self-attention of each query slot
across the frames, then an FFN (pre-norm residual blocks, as VPP's Video Former).
"""

from __future__ import annotations

import torch
from torch import nn

from trivla_drake.nn.attention import FeedForward, MultiHeadAttention


class VideoFormerLayer(nn.Module):
    """One spatial-attention, temporal-attention, FFN block over the queries."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.norm_spatial = nn.LayerNorm(dim)
        self.norm_context = nn.LayerNorm(dim)
        self.spatial = MultiHeadAttention(dim, num_heads)
        self.norm_temporal = nn.LayerNorm(dim)
        self.temporal = MultiHeadAttention(dim, num_heads)
        self.norm_ffn = nn.LayerNorm(dim)
        self.ffn = FeedForward(dim)

    def forward(self, queries: torch.Tensor, frame_tokens: torch.Tensor) -> torch.Tensor:
        """queries (B, T, L, D), frame_tokens (B, T, N, D) -> queries (B, T, L, D)."""
        batch, frames, slots, dim = queries.shape
        q = queries.flatten(0, 1)  # (B*T, L, D): Spat-Attn(Q[i], F_p[i]) frame by frame
        ctx = self.norm_context(frame_tokens.flatten(0, 1))
        q = q + self.spatial(self.norm_spatial(q), ctx)
        q = q.unflatten(0, (batch, frames)).transpose(1, 2).flatten(0, 1)  # (B*L, T, D): Temp-Attn
        q = q + self.temporal(self.norm_temporal(q))
        q = q + self.ffn(self.norm_ffn(q))
        return q.unflatten(0, (batch, slots)).transpose(1, 2)


class VideoFormer(nn.Module):
    """Learnable queries that aggregate multi-view, multi-frame features into Q_p (B, T*L, D)."""

    def __init__(
        self,
        feature_channels: int,
        num_frames: int,
        feature_size: int,
        dim: int,
        depth: int,
        num_heads: int,
        queries_per_frame: int,
        num_views: int = 2,
    ) -> None:
        super().__init__()
        self.num_frames = num_frames
        self.num_views = num_views
        self.feature_channels = feature_channels
        self.feature_size = feature_size
        self.input_norm = nn.LayerNorm(feature_channels)
        self.input_proj = nn.Linear(feature_channels, dim)
        self.spatial_pos = nn.Parameter(torch.randn(feature_size * feature_size, dim) * 0.02)
        self.view_embed = nn.Parameter(torch.randn(num_views, dim) * 0.02)
        self.queries = nn.Parameter(torch.randn(num_frames, queries_per_frame, dim) * 0.02)
        self.layers = nn.ModuleList([VideoFormerLayer(dim, num_heads) for _ in range(depth)])
        self.output_norm = nn.LayerNorm(dim)

    def tokens(self, views: list[torch.Tensor]) -> torch.Tensor:
        """Per-frame key/value tokens of all views: (B, T, V*H_p*W_p, D)."""
        out = []
        for v, features in enumerate(views):
            x = features.flatten(3).transpose(2, 3)  # (B, T, H_p*W_p, C)
            x = self.input_proj(self.input_norm(x)) + self.spatial_pos + self.view_embed[v]
            out.append(x)
        return torch.cat(out, dim=2)

    def forward(self, views: list[torch.Tensor]) -> torch.Tensor:
        """views: one F_p (B, T, C, H_p, W_p) per camera (static, wrist) -> Q_p (B, T*L, D)."""
        if len(views) != self.num_views:
            raise ValueError(f"the Video Former takes {self.num_views} views; got {len(views)}")
        expected = (self.num_frames, self.feature_channels, self.feature_size, self.feature_size)
        for features in views:
            if features.dim() != 5 or tuple(features.shape[1:]) != expected:
                raise ValueError(
                    f"dynamics features must be (B, {', '.join(map(str, expected))}); got {tuple(features.shape)}"
                )
        frame_tokens = self.tokens(views)
        q = self.queries.unsqueeze(0).expand(frame_tokens.shape[0], -1, -1, -1)
        for layer in self.layers:
            q = layer(q, frame_tokens)
        return self.output_norm(q.flatten(1, 2))
