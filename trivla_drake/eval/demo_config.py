"""`DemoConfig`, what `demo` runs: closed-loop episodes (or 5-task chains) of TriVLA as Drake systems, or of the
oracle (loadable from YAML: `trivla-drake demo --config FILE --set k=v`)."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc
from typing import Optional

from trivla_drake.eval.evaluate_config import EVAL_BASE_SEED, check_episode_count
from trivla_drake.eval.inference_config import InferenceConfig
from trivla_drake.eval.setting_checks import check_instruction_text, check_port, check_record_path, check_seconds

# The task `demo` runs when not told one.
DEMO_TASK = "place_in_bowl"


@dc.dataclass
class DemoConfig:
    """What `demo` runs."""

    # trivla (TriVLA as Drake systems) or oracle (the scripted expert, in the evaluation harness).
    policy: str = "trivla"
    # TriVLA checkpoint (None: models/trivla_cpu).
    checkpoint: Optional[str] = None
    # An UNTRAINED model of this preset (tiny, cpu) instead of a checkpoint: for wiring and timing, not success.
    preset: Optional[str] = None
    # Task name (None: place_in_bowl).
    task: Optional[str] = None
    # Say this instead of the task's own instruction (None: the task's).
    instruction: Optional[str] = None
    # Episodes of the task (None: 1).
    episodes: Optional[int] = None
    # Instead of episodes of one task, this many 5-task chains in one simulation each, the instruction changed as
    # each task is done (chain j starts as `evaluate --chains`'s chain j); reports Avg. Len (None: episodes).
    chains: Optional[int] = None
    # Base seed (scenes unseen by demonstrations collected with seed 0).
    seed: int = EVAL_BASE_SEED
    # Simulated inference latency: zero, measured (each inference's wall time) or a number of seconds.
    latency: str = "zero"
    # Episode time limit in sim seconds (None: the task's own limit).
    max_seconds: Optional[float] = None
    # Torch threads.
    threads: int = 1
    # TriVLA's sampling and chunk execution.
    inference: InferenceConfig = dc.field(default_factory=InferenceConfig)
    # Show the run live in Meshcat (localhost).
    meshcat: bool = False
    # Meshcat port (None: Drake's, 7000 up; 0: any free port).
    port: Optional[int] = None
    # Save the run as a self-contained HTML page here (None: no recording).
    record: Optional[str] = None

    def validate(self) -> None:
        """ValueError naming the flag or the dotted field of a setting that cannot run, before a model loads or a
        simulation runs (execute_steps' upper bound is the checkpoint's chunk length: checked once it loads)."""
        from trivla_drake.systems.latency import LatencyModel
        from trivla_drake.tasks.run_settings import check_run_settings

        if self.policy not in ("trivla", "oracle"):
            raise ValueError(f"--policy must be trivla or oracle, got {self.policy!r}")
        if self.chains is not None:
            check_episode_count(self.chains, "--chains")
            given = [flag for flag, value in (("--task", self.task), ("--instruction", self.instruction),
                                              ("--episodes", self.episodes)) if value is not None]
            if given:
                raise ValueError(f"--chains draws every chain's tasks and instructions: leave out {', '.join(given)}")
            if self.policy == "oracle":
                raise ValueError("--chains runs TriVLA as Drake systems; the oracle's chains: "
                                 "trivla-drake evaluate --policy oracle --episodes 0 --chains N")
        # `evaluate`'s checks of the task (an unknown name lists the valid ones) and --seed; then the rest.
        check_run_settings([self.task_name()], self.seed)
        check_episode_count(self.episode_count(), "--episodes")
        check_seconds(self.max_seconds, "max_seconds")
        check_instruction_text(self.instruction)
        check_port(self.port, "port")
        check_record_path(self.record)
        if self.preset is not None and self.preset not in ("tiny", "cpu"):
            raise ValueError(f"--preset must be tiny or cpu, got {self.preset!r}")
        if self.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.threads}")
        latency = LatencyModel.parse(self.latency)
        if self.policy == "oracle":
            if (self.meshcat or self.record or self.instruction or self.checkpoint or self.preset
                    or not self.inference.is_default() or latency.mode != "zero"):
                raise ValueError("--meshcat, --record, --instruction, --checkpoint, --preset, inference.* and "
                                 "--latency go with --policy trivla (the oracle runs in the evaluation harness, "
                                 "without latency)")
        self.inference.validate()

    def task_name(self) -> str:
        """The task the episodes run."""
        return self.task or DEMO_TASK

    def episode_count(self) -> int:
        """The episodes to run."""
        return 1 if self.episodes is None else self.episodes
