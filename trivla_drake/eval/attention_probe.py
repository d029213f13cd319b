"""Attention probes: can a reader that attends to System 2's image tokens, as System 1's
cross-attention does, tell where each block is?

A ridge probe on the flattened tokens (`feature_probe.ridge_probe`) knows which token each number
came from; an attention read-out does not, unless the tokens carry their position. This probe has
one learned query per block colour (several heads) that attends over the image tokens of both
views; values are a linear map of the tokens, and a linear layer maps what each query read to that
block's (x, y). With `positions`, a learned embedding per token position is added to the tokens
first: what `train --stage policy --vl-position-embedding` gives System 1. The probe is fitted with
Adam on a random 80% of the episodes and scored on the rest (held-out R^2 and RMSE, as the ridge).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

ATTENTION_PROBE_HEADS = 4
ATTENTION_PROBE_STEPS = 1500


class AttentionReadout(nn.Module):
    """Per block: `heads` learned queries attend over (B, T, D) tokens -> (B, blocks, 2)."""

    def __init__(self, tokens: int, dim: int, blocks: int, *, heads: int, positions: bool) -> None:
        super().__init__()
        self.queries = nn.Parameter(torch.randn(blocks, heads, dim) / dim**0.5)
        self.key = nn.Linear(dim, dim)
        self.value = nn.Linear(dim, dim)
        self.out = nn.Linear(heads * dim, 2)
        self.positions = nn.Parameter(torch.zeros(tokens, dim)) if positions else None

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        if self.positions is not None:
            tokens = tokens + self.positions
        weights = torch.einsum("khd,btd->bkht", self.queries, self.key(tokens)).softmax(dim=-1)
        read = torch.einsum("bkht,btd->bkhd", weights, self.value(tokens))
        return self.out(read.flatten(2))


def attention_probe(
    tokens: np.ndarray,
    targets: np.ndarray,
    *,
    positions: bool,
    steps: int = ATTENTION_PROBE_STEPS,
    held_out: float = 0.2,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Fits an `AttentionReadout` of tokens (N, T, D) to targets (N, 2 K) (x, y of K blocks) on
    1 - `held_out` of the episodes. Returns held-out R^2 (2 K,) and RMSE (2 K,) in target units."""
    x = np.asarray(tokens, dtype=np.float32)
    y = np.asarray(targets, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"tokens must be 3-D (episodes, tokens, dims); got shape {x.shape}")
    if y.ndim != 2 or y.shape[1] % 2:
        raise ValueError(f"targets must be (episodes, 2 * blocks); got shape {y.shape}")
    if x.shape[0] != y.shape[0]:
        raise ValueError(f"tokens has {x.shape[0]} rows but targets has {y.shape[0]}")
    if not 0 < held_out < 1 or round(held_out * len(x)) < 2 or len(x) - round(held_out * len(x)) < 2:
        raise ValueError(f"held_out must leave at least 2 episodes on each side; got {held_out} of {len(x)}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("tokens and targets must be finite")
    if steps < 1:
        raise ValueError(f"steps must be >= 1; got {steps}")
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(x))
    test, train = order[: round(held_out * len(x))], order[round(held_out * len(x)) :]
    mean, std = x[train].mean((0, 1)), x[train].std((0, 1)) + 1e-6
    y_mean, y_std = y[train].mean(0), y[train].std(0) + 1e-9
    xs = torch.from_numpy((x - mean) / std)
    ys = torch.from_numpy(((y - y_mean) / y_std).astype(np.float32)).view(len(y), -1, 2)
    generator = torch.Generator().manual_seed(seed)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        probe = AttentionReadout(x.shape[1], x.shape[2], ys.shape[1], heads=ATTENTION_PROBE_HEADS, positions=positions)
    optimizer = torch.optim.Adam(probe.parameters(), lr=1e-3)
    train_t = torch.from_numpy(train)
    with torch.enable_grad():
        for _ in range(steps):
            batch = train_t[torch.randint(len(train), (min(64, len(train)),), generator=generator)]
            loss = ((probe(xs[batch]) - ys[batch]) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    with torch.no_grad():
        predicted = probe(xs[torch.from_numpy(test)]).flatten(1).double().numpy() * y_std + y_mean
    error = ((predicted - y[test]) ** 2).mean(0)
    return 1.0 - error / (y[test].var(0) + 1e-12), np.sqrt(error)
