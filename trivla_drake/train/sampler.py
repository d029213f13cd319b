"""A distributed, resumable batch sampler: the batch of every (step, rank) is a pure function of
(seed, step, rank, world size), so a resumed run continues with exactly the batches it would have seen.

Epoch e shuffles all N sample indices with a generator seeded by (seed, e); rank r takes every
world-th index starting at r (the padding of DistributedSampler: the permutation is extended by its
own head so every rank gets the same number); each rank then cuts its share into batches and drops
the incomplete last one. Step s is batch s % steps_per_epoch of epoch s // steps_per_epoch.
"""

from __future__ import annotations

from typing import Iterator

import torch


class StepBatchSampler:
    """Yields the index batches of steps `start_step` .. `total_steps - 1` for one rank."""

    def __init__(
        self,
        num_samples: int,
        batch_size: int,
        *,
        seed: int,
        rank: int = 0,
        world_size: int = 1,
        start_step: int = 0,
        total_steps: int,
        shuffle: bool = True,
    ) -> None:
        if num_samples < 1:
            raise ValueError("the dataset has no training samples")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} not in [0, {world_size})")
        self.num_samples, self.batch_size = num_samples, batch_size
        self.seed, self.rank, self.world_size = seed, rank, world_size
        self.start_step, self.total_steps, self.shuffle = start_step, total_steps, shuffle
        self.per_rank = -(-num_samples // world_size)  # ceil
        # Fewer samples per rank than a batch: batches then wrap around the (reshuffled) data.
        self.steps_per_epoch = max(1, self.per_rank // batch_size)
        self._cache: tuple[int, torch.Tensor] | None = None

    def _rank_indices(self, epoch: int) -> torch.Tensor:
        if self._cache is not None and self._cache[0] == epoch:
            return self._cache[1]
        if self.shuffle:
            g = torch.Generator().manual_seed((self.seed * 1_000_003 + epoch) % (2**63 - 1))
            perm = torch.randperm(self.num_samples, generator=g)
        else:
            perm = torch.arange(self.num_samples)
        total = self.per_rank * self.world_size
        if total > len(perm):
            perm = torch.cat([perm, perm.repeat(-(-total // len(perm)))[: total - len(perm)]])
        share = perm[self.rank : total : self.world_size]
        need = self.steps_per_epoch * self.batch_size
        if len(share) < need:
            share = share.repeat(-(-need // len(share)))[:need]
        self._cache = (epoch, share)
        return share

    def batch_at(self, step: int) -> list[int]:
        """This rank's sample indices for optimizer step `step`."""
        epoch, k = divmod(step, self.steps_per_epoch)
        share = self._rank_indices(epoch)
        return share[k * self.batch_size : (k + 1) * self.batch_size].tolist()

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.start_step, self.total_steps):
            yield self.batch_at(step)

    def __len__(self) -> int:
        return max(0, self.total_steps - self.start_step)
