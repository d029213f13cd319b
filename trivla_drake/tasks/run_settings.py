"""The run settings `collect`, `evaluate`, `demo` and `tables` share, checked before anything runs: the suite's task
names and a 32-bit seed."""

from __future__ import annotations

import numpy as np

from trivla_drake.tasks.suite import get_task

# Seeds are 32-bit words (eval/episode.py's derive_seed): a larger one would wrap onto another's scenes.
MAX_SEED = 2**32 - 1


def check_seed(seed: int, flag: str = "--seed") -> int:
    """`seed` if it is an integer from 0 to MAX_SEED; else ValueError naming `flag`."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"{flag} must be an integer from 0 to {MAX_SEED} (a 32-bit seed; a larger one would wrap "
                         f"onto another's scenes), got {seed!r}")
    return seed


def check_run_settings(tasks: list[str], seed: int) -> None:
    """What `collect` and `evaluate` both refuse, naming the flag: an unknown task, a task named twice (the same
    seeds twice), or a seed outside 0..MAX_SEED."""
    for name in tasks:
        get_task(name)
    repeated = sorted(name for name in set(tasks) if tasks.count(name) > 1)
    if repeated:
        raise ValueError(f"--tasks names {repeated} more than once")
    check_seed(seed)
