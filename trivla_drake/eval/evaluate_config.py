"""`EvalConfig`, what `evaluate` runs (loadable from YAML: `trivla-drake evaluate --config FILE --set k=v`), and the
bounds of its counts and seeds."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc
from typing import Optional

from trivla_drake.eval.inference_config import InferenceConfig
from trivla_drake.eval.plugin_config import PluginConfig
from trivla_drake.tasks.chains import CHAIN_LENGTH
from trivla_drake.tasks.run_settings import check_run_settings
from trivla_drake.tasks.suite import TASK_NAMES

# Default base seed of evaluations: `collect` uses base seed 0, so these scenes are unseen by the
# demonstrations (tests check the two seed sets are disjoint).
EVAL_BASE_SEED = 1000
# The most episodes per task (or chains) one run takes: more would run for months (an episode takes seconds), and a
# number such as 10**20 is a typo to refuse before anything runs.
MAX_EPISODES = 100_000
# Where `evaluate --chains` takes its chains from (see EvalConfig.chain_source).
CHAIN_SOURCES = ("benchmark", "drawn")


@dc.dataclass
class EvalConfig:
    """What `evaluate` runs."""

    # 'oracle', 'random', 'trivla' (the shipped checkpoint) or a checkpoint path.
    policy: str = "oracle"
    # Task names of the single-task episodes (all tasks by default).
    tasks: list[str] = dc.field(default_factory=lambda: list(TASK_NAMES))
    # Episodes per task (0: chains only).
    episodes: int = 10
    # Base seed of every episode's and chain's randomness.
    seed: int = EVAL_BASE_SEED
    # Base seeds to run in one call (None: [seed]), e.g. [1000, 1001, 1002] (`--seeds 1000-1002`); the report then has
    # each seed's figures and the pooled ones.
    seeds: Optional[list[int]] = None
    # Chains of five tasks to run (0: none): the first `chains` of the fixed benchmark (tasks/chain_benchmark.py, at
    # most BENCHMARK_CHAINS), or, with chain_source "drawn", chains drawn from each seed.
    chains: int = 0
    # "benchmark": the fixed chains shipped with the package, chain j's scene and tasks the same whoever runs it (the
    # seed draws the policy's noise only); "drawn": each chain drawn from the seed as it goes (reports before the
    # benchmark existed, session 69).
    chain_source: str = "benchmark"
    # Instructions from the held-out paraphrases instead of the training templates.
    paraphrases: bool = False
    # Local worker processes (1: in this process; more: a local Ray with that many, started and stopped by the
    # command). Ignored with ray_address.
    workers: int = 1
    # An existing Ray cluster to run on (e.g. 'ray://head:10001' or 'auto'; None: $RAY_ADDRESS if set, else
    # local). The results are the same as a serial run's, whatever the cluster's size.
    ray_address: Optional[str] = None
    # Torch threads of a serial run (each worker process uses 1, so TriVLA's results do not depend on workers:
    # `rollout_threads`).
    threads: int = 1
    # Folder for report.json, report.md, report.png (eval/report_plot.py), eval_config.yaml and episodes.jsonl, every
    # result as it comes (eval/evaluation_journal.py: a killed run resumes, a larger one reuses it); None: the report is only printed and nothing resumes.
    out: Optional[str] = None
    # Folder for one mp4 per episode / chain (None: no videos).
    record_dir: Optional[str] = None
    # Image size for policies that look (None: 224 when images are needed, else no rendering).
    image_size: Optional[int] = None
    # Cap on the steps of every episode (None: each task's own max_steps); for quick runs.
    max_steps: Optional[int] = None
    # TriVLA's sampling and chunk execution (other policies take none of it).
    inference: InferenceConfig = dc.field(default_factory=InferenceConfig)
    # Episodes start after the oracle has completed this many other tasks of a chain (unrecorded), where
    # a chain's later tasks start (0: from the start posture). A prelude that fails or leaves the task no
    # way to start is redrawn (it is no failure of the policy).
    prelude: int = 0
    # Registered policy wrappers (eval/policy_wrappers.py) around the policy, the first innermost; e.g.
    # [{name: home_first}] (learned policies: every task that does not start the episode first homes the hand).
    policy_wrappers: list[PluginConfig] = dc.field(default_factory=list)
    # Seconds the hand is held still after each success (the gripper keeping its last command) before the task's
    # predicate is asked again; the report then also counts the successes that lasted (None: no hold check).
    # Successes are still counted when the predicate first holds, as CALVIN counts them. Single tasks are then the
    # runs without the hold; in chains the next task starts after the hold, so the chains themselves differ.
    hold_check: Optional[float] = None

    def validate(self) -> None:
        """ValueError naming the flag or the dotted field of a setting that cannot run."""
        check_episode_count(self.episodes, "--episodes", minimum=0)
        check_episode_count(self.chains, "--chains", minimum=0)
        if (not self.tasks or not self.episodes) and self.chains <= 0:
            raise ValueError("nothing to evaluate: give --tasks with --episodes >= 1, or --chains >= 1")
        for seed in self.seed_list():
            check_run_settings(self.tasks, seed)
        if self.seeds is not None and (not self.seeds or len(set(self.seeds)) != len(self.seeds)):
            raise ValueError(f"--seeds must be distinct base seeds, at least one, got {self.seeds}")
        if self.chain_source not in CHAIN_SOURCES:
            raise ValueError(f"chain_source must be one of {', '.join(CHAIN_SOURCES)}, got {self.chain_source!r}")
        if self.chains and self.chain_source == "benchmark":
            from trivla_drake.tasks.chain_benchmark import BENCHMARK_SIZE as BENCHMARK_CHAINS

            if self.chains > BENCHMARK_CHAINS:
                raise ValueError(f"--chains must be at most {BENCHMARK_CHAINS} (the fixed benchmark's chains), got "
                                 f"{self.chains}; more chains: --seeds (the same chains with other policy noise) or "
                                 "--set chain_source=drawn")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise ValueError(f"--workers must be an integer >= 1, got {self.workers!r}")
        if isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.threads!r}")
        if isinstance(self.prelude, bool) or not isinstance(self.prelude, int) or not 0 <= self.prelude < CHAIN_LENGTH:
            raise ValueError(f"prelude must be an integer from 0 to {CHAIN_LENGTH - 1}, got {self.prelude!r}")
        self.inference.validate()  # the chunk length is the checkpoint's: loading it checks execute_steps' bound
        from trivla_drake.eval.episode import check_hold_check

        check_hold_check(self.hold_check, "hold_check")
        from trivla_drake.eval.policy_wrappers import check_policy_wrappers

        check_policy_wrappers(self.policy_wrappers)
        if any(wrapper.name == "home_first" for wrapper in self.policy_wrappers) and self.policy == "oracle":
            raise ValueError("policy_wrappers: home_first applies to learned policies, not to --policy oracle (it "
                             "plans from wherever the hand is)")

    def rollout_threads(self) -> int:
        """The torch threads each rollout runs with: `threads` in a serial run, 1 in a Ray worker (and in this
        process when a Ray run has a single job left), so a run's results do not depend on its workers."""
        from trivla_drake.eval.rollout_runner import resolve_address

        return self.threads if self.workers == 1 and resolve_address(self.ray_address) is None else 1

    def seed_list(self) -> list[int]:
        """The base seeds this config runs, in order."""
        return [self.seed] if self.seeds is None else list(self.seeds)

    def policy_key(self) -> tuple:
        """What loads this config's policy (see evaluate's `_policy`): hashable."""
        inference = self.inference
        return (self.policy, inference.noise_scale, inference.execute_steps, inference.ensemble_decay,
                tuple(wrapper.key() for wrapper in self.policy_wrappers))


def check_episode_count(count: int, flag: str, *, minimum: int = 1) -> int:
    """`count` if it is an integer from `minimum` to MAX_EPISODES; else ValueError naming `flag` and the range."""
    if isinstance(count, bool) or not isinstance(count, int) or not minimum <= count <= MAX_EPISODES:
        raise ValueError(f"{flag} must be at least {minimum} and at most {MAX_EPISODES} (an integer; MAX_EPISODES: a "
                         f"larger run would take months, split it into runs of other seeds), got {count!r}")
    return count


def parse_seeds(text: str, flag: str = "--seeds") -> list[int]:
    """The base seeds of a flag such as '1000-1017' (a range, both ends included) or '1000,1005,1010' (a list; the
    two mix: '1000-1002,2000'); ValueError naming `flag` (their range is the config's to check)."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            first, sep, last = part.strip().partition("-")
            if sep and first:  # a range (not a negative number, which the config refuses)
                low, high = int(first), int(last)
                if high < low or high - low >= MAX_EPISODES:
                    raise ValueError
                seeds.extend(range(low, high + 1))
            else:
                seeds.append(int(part))
    except ValueError:
        raise ValueError(f"{flag} must be base seeds as a range or a comma-separated list, e.g. 1000-1017 or "
                         f"1000,1001,1002; got {text!r}") from None
    return seeds
