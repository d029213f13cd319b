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
    # Chains of five tasks to run (0: none).
    chains: int = 0
    # Instructions from the held-out paraphrases instead of the training templates.
    paraphrases: bool = False
    # Processes to run episodes in (1: in this process).
    workers: int = 1
    # Torch threads of a serial run (each worker process uses 1, so TriVLA's results do not depend on workers).
    threads: int = 1
    # Folder for report.json and eval_config.yaml (None: the report is only printed).
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
        check_run_settings(self.tasks, self.seed)
        if self.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {self.workers}")
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
