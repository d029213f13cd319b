"""Embodiment-specific layers (GR00T's design): one weight matrix per embodiment in a single tensor
W[num_embodiments, in, out], selected per sample by its embodiment id (a batched matmul)."""

from __future__ import annotations

import math

import torch
from torch import nn


def check_embodiment_ids(embodiment_id: torch.Tensor, num_embodiments: int) -> None:
    """Raises ValueError naming `embodiment_id` unless every id is in [0, num_embodiments)."""
    if embodiment_id.dtype not in (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8):
        raise ValueError(f"embodiment_id must be integers; got dtype {embodiment_id.dtype}")
    if embodiment_id.numel() and (embodiment_id.min() < 0 or embodiment_id.max() >= num_embodiments):
        raise ValueError(
            f"embodiment_id must be in [0, {num_embodiments}) (policy.num_embodiments); "
            f"got {sorted(set(embodiment_id.flatten().tolist()))}"
        )


class EmbodimentLinear(nn.Module):
    """y = x W[e] + b[e] with a separate (in, out) matrix for each embodiment e."""

    def __init__(self, num_embodiments: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.num_embodiments = num_embodiments
        self.weight = nn.Parameter(torch.empty(num_embodiments, in_features, out_features))
        self.bias = nn.Parameter(torch.empty(num_embodiments, out_features))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Each embodiment's slice gets its own draw of nn.Linear's default uniform initialisation."""
        bound = 1.0 / math.sqrt(self.weight.shape[1])
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor, embodiment_id: torch.Tensor) -> torch.Tensor:
        """x: (B, ..., in), embodiment_id: (B,) long -> (B, ..., out)."""
        # index_select, not self.weight[embodiment_id]: the gradient of advanced indexing accumulates
        # with atomic adds across CPU threads, so two runs from one seed would differ in rounding.
        ids = embodiment_id.long()
        w = self.weight.index_select(0, ids)  # (B, in, out)
        b = self.bias.index_select(0, ids)  # (B, out)
        flat = x.reshape(x.shape[0], -1, x.shape[-1])
        out = torch.bmm(flat, w) + b.unsqueeze(1)
        return out.reshape(*x.shape[:-1], out.shape[-1])


class EmbodimentMLP(nn.Module):
    """Two embodiment-specific linear layers with a SiLU between them."""

    def __init__(self, num_embodiments: int, in_features: int, hidden: int, out_features: int) -> None:
        super().__init__()
        self.fc1 = EmbodimentLinear(num_embodiments, in_features, hidden)
        self.fc2 = EmbodimentLinear(num_embodiments, hidden, out_features)

    def forward(self, x: torch.Tensor, embodiment_id: torch.Tensor) -> torch.Tensor:
        """x: (B, ..., in) -> (B, ..., out) with embodiment `embodiment_id[b]`'s weights for sample b."""
        return self.fc2(torch.nn.functional.silu(self.fc1(x, embodiment_id)), embodiment_id)
