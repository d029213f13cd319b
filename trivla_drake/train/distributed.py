"""Single-process or `torchrun` (DistributedDataParallel) execution, detected from the environment.

torchrun sets RANK, WORLD_SIZE and LOCAL_RANK; without them training runs in one process. The process
group uses NCCL when CUDA is available and gloo otherwise (CPU).
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class DistEnv:
    """This process's place in the job."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def distributed(self) -> bool:
        """More than one process."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that writes checkpoints and shows progress."""
        return self.rank == 0

    def barrier(self) -> None:
        """Waits for every process (no-op in one process)."""
        if self.distributed:
            dist.barrier()

    def all_gather_object(self, obj: Any) -> list[Any]:
        """Every rank's `obj`, in rank order (a one-element list in one process)."""
        if not self.distributed:
            return [obj]
        out: list[Any] = [None] * self.world_size
        dist.all_gather_object(out, obj)
        return out

    def broadcast_object(self, obj: Any) -> Any:
        """Rank 0's `obj` on every rank."""
        if not self.distributed:
            return obj
        box = [obj]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def mean(self, value: float) -> float:
        """The mean of a float over ranks."""
        if not self.distributed:
            return float(value)
        t = torch.tensor([float(value)], dtype=torch.float64, device=self._collective_device)
        dist.all_reduce(t)
        return float(t.item()) / self.world_size

    @property
    def _collective_device(self) -> torch.device:
        return self.device if self.device.type == "cuda" else torch.device("cpu")


def _env_int(name: str) -> int | None:
    value = os.environ.get(name)
    if value is None or value == "":
        return None
    try:
        return int(value)
    except ValueError as exc:
        raise ValueError(f"environment variable {name} must be an integer; got {value!r}") from exc


def setup_distributed(timeout_minutes: float = 120.0) -> DistEnv:
    """Reads RANK / WORLD_SIZE / LOCAL_RANK, initialises the process group when WORLD_SIZE > 1
    (nccl on CUDA, gloo on CPU) and picks this process's device (cuda:LOCAL_RANK or cpu)."""
    world = _env_int("WORLD_SIZE") or 1
    rank = _env_int("RANK") or 0
    local = _env_int("LOCAL_RANK")
    local = rank if local is None else local
    if not 0 <= rank < world:
        raise ValueError(f"RANK ({rank}) must be in [0, WORLD_SIZE={world})")
    cuda = torch.cuda.is_available()
    device = torch.device("cuda", local % max(torch.cuda.device_count(), 1)) if cuda else torch.device("cpu")
    if cuda:
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group(
            backend="nccl" if cuda else "gloo",
            timeout=datetime.timedelta(minutes=timeout_minutes),
            **({"device_id": device} if cuda else {}),
        )
    return DistEnv(rank=rank, world_size=world, local_rank=local, device=device)


def teardown_distributed(env: DistEnv) -> None:
    """Destroys the process group set up by `setup_distributed`."""
    if env.distributed and dist.is_initialized():
        dist.destroy_process_group()
