"""The random states of a training run: the flow/diffusion noise generator of each rank and the global torch, CUDA,
numpy and Python generators, as a checkpoint stores them and a resumed run restores them."""

from __future__ import annotations

import hashlib
import random
from typing import Any

import numpy as np
import torch


def rank_seed(seed: int, rank: int) -> int:
    """The seed of rank `rank`'s noise generator in a run seeded with `seed`."""
    return int(hashlib.sha256(f"noise:{seed}:{rank}".encode()).hexdigest()[:15], 16)


def rng_state(generator: torch.Generator) -> dict[str, Any]:
    """`generator`'s state and the global generators' (what a checkpoint stores per rank)."""
    np_state = np.random.get_state()
    return {
        "noise": generator.get_state(),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": [np_state[0], np_state[1].tolist(), int(np_state[2]), int(np_state[3]), float(np_state[4])],
        "python": random.getstate(),
    }


def set_rng_state(state: dict[str, Any], generator: torch.Generator) -> None:
    """Restores `rng_state`'s `state` into `generator` and the global generators."""
    generator.set_state(state["noise"])
    torch.set_rng_state(state["torch"])
    if torch.cuda.is_available() and state.get("cuda"):
        torch.cuda.set_rng_state_all(state["cuda"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    random.setstate(_as_tuples(state["python"]))


def _as_tuples(value: Any) -> Any:
    return tuple(_as_tuples(v) for v in value) if isinstance(value, (list, tuple)) else value
