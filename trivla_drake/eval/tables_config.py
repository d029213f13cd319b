"""`TablesConfig`, what `tables` runs (loadable from YAML: `trivla-drake tables --config FILE --set k=v`; a report
keeps its own as OUT/tables_config.yaml)."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc
from pathlib import Path
from typing import Optional

from trivla_drake.eval.evaluate_config import EVAL_BASE_SEED, EvalConfig, check_episode_count
from trivla_drake.eval.inference_config import InferenceConfig
from trivla_drake.tasks.suite import TASK_NAMES

ROLES = ("full", "system1_3", "system1", "data10")


@dc.dataclass
class TablesConfig:
    """What `make_tables` runs; every default is the issue's minimum."""

    # Checkpoint directory per role: full (Systems 1+2+3, all demonstrations; required), system1_3 (trained
    # without System 2), system1 (without Systems 2 and 3), data10 (10% of the demonstrations); a missing role
    # leaves its rows out.
    checkpoints: dict[str, str] = dc.field(default_factory=dict)
    # Folder for report.md, report.json, the plots and tables_config.yaml (None: the caller writes nothing).
    out: Optional[str] = None
    # Tasks (all by default).
    tasks: list[str] = dc.field(default_factory=lambda: list(TASK_NAMES))
    # Episodes per task and seed.
    episodes: int = 5
    # Base seeds: each is a full evaluation, the spread across them is the standard error.
    seeds: list[int] = dc.field(default_factory=lambda: [EVAL_BASE_SEED + i for i in range(3)])
    # 5-task chains per seed, for Avg. Len: the first `chains` of the fixed benchmark (the same chains for every seed,
    # each seed drawing the policy's noise), or with chain_source "drawn" chains drawn from each seed.
    chains: int = 5
    # Where the chains come from (EvalConfig.chain_source): "benchmark" or "drawn" (tables before session 69).
    chain_source: str = "benchmark"
    # Episodes per task for the latency comparison (Drake systems, slower than the harness).
    latency_episodes: int = 2
    # Tasks for the latency comparison.
    latency_tasks: list[str] = dc.field(default_factory=lambda: ["lift_block", "turn_on_light", "open_drawer"])
    # Local worker processes (1: in this process; more: a local Ray with that many, started and stopped by the
    # command). Ignored with ray_address.
    workers: int = 1
    # An existing Ray cluster to run on (e.g. 'ray://head:10001' or 'auto'; None: $RAY_ADDRESS if set, else
    # local). The results are the same as a serial run's, whatever the cluster's size.
    ray_address: Optional[str] = None
    # Cap on steps per episode (None: each task's own).
    max_steps: Optional[int] = None
    # Store each evaluation (one checkpoint, seed and setting) and reuse the stored ones, so a killed or extended
    # run redoes only what is missing (false: store and reuse none).
    reuse: bool = True
    # Folder of stored evaluations to reuse and add to, e.g. another report's (None: OUT/evaluations when `out`
    # is set, else none).
    results_dir: Optional[str] = None
    # Every checkpoint's TriVLA inference settings (see EvalConfig.inference).
    inference: InferenceConfig = dc.field(default_factory=InferenceConfig)
    # Torch threads of this process (workers use 1 each); part of the storage key when not 1.
    threads: int = 1

    def evaluations_dir(self) -> Optional[str]:
        """Where evaluations are stored and reused (None: nowhere)."""
        if not self.reuse:
            return None
        if self.results_dir is not None:
            return self.results_dir
        return str(Path(self.out) / "evaluations") if self.out else None

    def validate(self) -> None:
        """ValueError naming the flag or the dotted field of a setting that cannot run."""
        from trivla_drake.tasks import get_task
        from trivla_drake.tasks.run_settings import check_seed

        if not self.seeds:
            raise ValueError("--seeds is empty: give one or more comma-separated base seeds, e.g. 1000,1001,1002")
        for seed in self.seeds:
            check_seed(seed, "--seeds")  # evaluate's range for its --seed, before anything runs
        from trivla_drake.eval.evaluate_config import CHAIN_SOURCES

        if self.chain_source not in CHAIN_SOURCES:
            raise ValueError(f"chain_source must be one of {', '.join(CHAIN_SOURCES)}, got {self.chain_source!r}")
        repeated = sorted({seed for seed in self.seeds if self.seeds.count(seed) > 1})
        if repeated:
            raise ValueError(f"--seeds names {repeated} more than once (each seed is one sample of the stderr)")
        for name in [*self.tasks, *self.latency_tasks]:
            get_task(name)  # ValueError naming the unknown task
        unknown = sorted(set(self.checkpoints) - set(ROLES))
        if unknown:
            raise ValueError(f"checkpoint roles {unknown} are unknown; valid roles: {', '.join(ROLES)}")
        if "full" not in self.checkpoints:
            raise ValueError("checkpoints needs a 'full' entry (Systems 1+2+3 on all demonstrations; --full)")
        for role, path in self.checkpoints.items():
            if not (Path(path) / "config.json").exists():
                raise ValueError(f"--{role.replace('_', '-')} {path} is not a checkpoint directory (no config.json)")
        if self.episodes < 1:
            raise ValueError(f"--episodes must be at least 1, got {self.episodes}")
        check_episode_count(self.latency_episodes, "latency_episodes", minimum=0)
        if self.results_dir is not None and not self.reuse:
            raise ValueError("results_dir names a folder of evaluations to reuse, and reuse is false: set one")
        if isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.threads!r}")
        # TriVLA's inference settings get `evaluate`'s checks (the chunk length is checked when each
        # checkpoint loads).
        EvalConfig(policy="trivla", tasks=list(self.tasks), episodes=self.episodes, chains=self.chains,
                   inference=self.inference).validate()
