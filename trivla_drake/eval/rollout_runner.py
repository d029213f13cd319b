"""Where rollouts run: in this process, on a local Ray started for the command, or on an existing Ray cluster.

    with RolloutRunner(workers=2) as runner:                       # local Ray, 2 worker processes
        for result in runner.map_ordered(function, config, jobs):  # function(config, job) in the jobs' order
            ...
    RolloutRunner(workers=1)                                       # serial, in this process (no Ray)
    RolloutRunner(address="ray://head:10001")                      # an existing cluster (or RAY_ADDRESS)

Results come back in the jobs' order whatever order the workers finish in, so a run gives exactly what a serial run
gives (`collect` stays its dataset's single writer: workers return episodes, the driver commits them). Jobs are drawn
lazily, a few per worker ahead of the one awaited, so a long job list is never listed up front. A worker process that
dies is replaced and its job re-run (`MAX_RETRIES` times); a job that raises, or that kills its worker every time,
stops the run with `RolloutError` naming the job (the driver has then committed every job before it).

`function` and `config` must be picklable (a module-level function and a dataclass); each worker process keeps its
module state between jobs (a loaded policy, a built simulation), as one process of the old pool did.
"""

from __future__ import annotations

import itertools
import logging
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any

# Ray re-runs a job whose worker process died this many times before it reports the job failed.
MAX_RETRIES = 2
# Jobs in flight per worker beyond the one the driver awaits (keeps every worker busy while results are re-ordered).
AHEAD_PER_WORKER = 4
# The local Ray's shared-object store [bytes]: results are a few MB at most (an episode's states and videos).
LOCAL_OBJECT_STORE_BYTES = 512 * 1024 * 1024
ADDRESS_ENV = "RAY_ADDRESS"
# Environment variables the workers get from the driver (nn/text_encoder.py's OVERRIDE_ENV; not imported: torch).
FORWARDED_ENV = ("TRIVLA_DRAKE_TEXT_ENCODER",)


class RolloutError(RuntimeError):
    """A job failed on a worker (its exception, or its worker died more than MAX_RETRIES times)."""


class WorkerDiedError(RolloutError):
    """A job whose worker died more than MAX_RETRIES times (not the job's own exception: a rerun may get through)."""


def setup_worker_process() -> None:
    """What every worker process does once before its first job: one torch thread (one process per core; threads would
    only fight over the cores, and results must not depend on the number of workers) and Drake's chatter off."""
    logging.getLogger("drake").setLevel(logging.ERROR)
    import torch

    torch.set_num_threads(1)


_WORKER_READY = False


def _run_in_worker(function: Callable[[Any, Any], Any], config: Any, job: Any) -> Any:
    """`function(config, job)` on a worker, after the process's one-time setup."""
    global _WORKER_READY
    if not _WORKER_READY:
        setup_worker_process()
        _WORKER_READY = True
    return function(config, job)


def forwarded_env() -> dict[str, str]:
    """The driver's settings every worker needs too: the text encoder a run's checkpoints read
    (`trivla-drake --text-encoder`, $TRIVLA_DRAKE_TEXT_ENCODER; on a cluster, a folder every node has)."""
    return {name: os.environ[name] for name in FORWARDED_ENV if os.environ.get(name)}


def start_local_ray(workers: int) -> None:
    """`ray.init` of a local Ray with `workers` worker CPUs for rollouts: no dashboard, a small object store, one
    thread per worker, and workers at the driver's priority (Ray's default lowers theirs, niceness 15, so any other
    process on the machine, e.g. another job, would starve them)."""
    import ray

    ray.init(address="local", num_cpus=workers, include_dashboard=False, object_store_memory=LOCAL_OBJECT_STORE_BYTES,
             logging_level=logging.WARNING, runtime_env={"env_vars": {"OMP_NUM_THREADS": "1", **forwarded_env()}},
             _system_config={"worker_niceness": 0})


def resolve_address(address: str | None) -> str | None:
    """The Ray cluster to join: `address` if given, else $RAY_ADDRESS, else None (no cluster: a local Ray or none)."""
    address = address if address else os.environ.get(ADDRESS_ENV) or None
    if address is not None and not isinstance(address, str):
        raise ValueError(f"ray_address must be a string such as 'ray://head:10001' or 'auto', got {address!r}")
    return address


def check_workers(workers: int, field: str = "--workers") -> int:
    """`workers` if it is an integer >= 1; else ValueError naming `field`."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"{field} must be an integer >= 1, got {workers!r}")
    return workers


class RolloutRunner:
    """Runs `function(config, job)` for a stream of jobs, serially or as Ray tasks (see the module docstring).

    `workers` is the number of local worker processes (1: serial, in this process, no Ray). With an `address` (or
    $RAY_ADDRESS) the jobs go to that cluster instead and `workers` is ignored: as many run at once as it has CPUs.
    A Ray this runner starts is stopped on exit; one that was already running (a cluster joined, or `ray.init` called
    by the caller) is left running.
    """

    def __init__(self, workers: int = 1, address: str | None = None):
        self.workers = check_workers(workers)
        self.address = resolve_address(address)
        self._ray = None
        self._started_ray = False
        self._remote = None

    @property
    def uses_ray(self) -> bool:
        return self.address is not None or self.workers > 1

    def __enter__(self) -> RolloutRunner:
        if not self.uses_ray:
            return self
        import ray

        self._ray = ray
        if not ray.is_initialized():
            if self.address is not None:
                env = forwarded_env()
                ray.init(address=self.address, logging_level=logging.WARNING, log_to_driver=True,
                         runtime_env={"env_vars": env} if env else None)
            else:
                # RAY_ADDRESS must not send a local run to a cluster it did not ask for (resolve_address read it).
                start_local_ray(self.workers)
            self._started_ray = True
        self._remote = ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(_run_in_worker)
        return self

    def __exit__(self, *exc) -> None:
        if self._started_ray:
            self._ray.shutdown()
        self._ray, self._remote, self._started_ray = None, None, False

    def parallelism(self) -> int:
        """How many jobs run at once: 1 serially, the local workers, or the cluster's CPUs."""
        if not self.uses_ray:
            return 1
        if self._ray is None:
            raise RuntimeError("RolloutRunner: use it in a `with` block")
        if self.address is None and self._started_ray:
            return self.workers
        return max(1, int(self._ray.cluster_resources().get("CPU", 1)))

    def map_ordered(self, function: Callable[[Any, Any], Any], config: Any, jobs: Iterable,
                    *, describe: Callable[[Any], str] = repr) -> Iterator:
        """`function(config, job)` of each job, yielded in the jobs' order; `describe(job)` names a failed job."""
        if not self.uses_ray:
            for job in jobs:
                yield function(config, job)
            return
        if self._remote is None:
            raise RuntimeError("RolloutRunner: use it in a `with` block")
        ray = self._ray
        config_ref = ray.put(config)  # shipped to the workers once, not with every job
        jobs = iter(jobs)
        ahead = AHEAD_PER_WORKER * self.parallelism()
        pending: deque = deque()

        def submit(count: int) -> None:
            for job in itertools.islice(jobs, count):
                pending.append((job, self._remote.remote(function, config_ref, job)))

        submit(ahead)
        try:
            while pending:
                job, ref = pending.popleft()
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayTaskError as error:  # the job raised: its own exception, with the job named
                    cause = getattr(error, "cause", None) or error  # the job's own exception (its traceback: below)
                    raise RolloutError(f"{describe(job)} failed on a worker: {type(cause).__name__}: {cause}") from error
                except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                        ray.exceptions.RayError) as error:
                    raise WorkerDiedError(f"{describe(job)}: its worker died {MAX_RETRIES + 1} times "
                                       f"({type(error).__name__}); nothing after it was committed") from error
                submit(1)
                yield result
        finally:
            for _, ref in pending:  # an abandoned run (an error, or the caller stopped reading): stop its jobs
                ray.cancel(ref, force=True)
