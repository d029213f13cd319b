"""Policy takeovers for demonstration collection: a learned policy drives, then the expert takes over
(DAgger-style data, Ross et al. 2011, collected as in HG-DAgger: the expert labels the states the
learned policy reaches).

The shipped policy's grasps fail 2-3 cm off the block (results/missed_grasps). The synthetic
disturbances so far (bursts, yaw twists, missed grasps, approach drifts) put the hand in states
we chose. `PolicyTakeover` instead puts it where the learned policy itself takes it. At the start
of each episode the learned policy (a TriVLA checkpoint, run as in `evaluate`) drives for a number
of control steps drawn from `steps`. It hands back earlier the first time it commands the gripper
closed; that close is not applied. Then the expert (`OraclePolicy(align_first=True,
resume_descent=True)`) drives to the end.

The recorded action of every frame is the expert's: what it would do in the state the policy
reached. The policy's steps are marked disturbed (`Trajectory.perturbed`), so training keeps the
expert's own action as a label for those frames (row 0 of their chunks) and masks the later rows
(`trivla_drake.data.samples`). At the handback the expert plans the task again from the scene as
it is (`OraclePolicy.replan`: the policy may have moved a block), and with `resume_descent` it picks
its leg from where the hand is: in the funnel above the grasp it aligns across and turns at that
height and then goes down; lower or farther off, it rises and moves across into the funnel first.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_POLICY_READS = frozenset({"static_rgb", "wrist_rgb", "state", "instruction"})

# One model per checkpoint folder and process: collection workers run many episodes each.
_MODELS: dict[str, object] = {}


def _harness_policy(checkpoint: str, execute_steps: int | None):
    from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy
    from trivla_drake.nn import load_checkpoint

    key = str(Path(checkpoint).resolve())
    if key not in _MODELS:
        _MODELS[key] = load_checkpoint(key).eval()
    return TriVLAHarnessPolicy(_MODELS[key], execute_steps=execute_steps)


@dataclass(frozen=True)
class PolicyTakeover:
    """Settings of the takeover (see the module docstring)."""

    # TriVLA checkpoint folder of the policy that drives first.
    checkpoint: str
    # Control steps the policy drives, drawn uniformly from this range (inclusive); fewer when it
    # commands the gripper closed first.
    steps: tuple[int, int] = (30, 150)
    # Actions of each chunk the policy executes before it predicts again (None: the whole chunk).
    execute_steps: int | None = None
    # The expert of the episode (an OraclePolicy): told to `replan()` from the scene as it is when the
    # policy hands back, since the policy may have moved a block. None: nobody is told.
    expert: object = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not (Path(self.checkpoint) / "config.json").is_file():
            raise ValueError(f"--takeover: {self.checkpoint!r} is not a TriVLA checkpoint folder "
                             "(no config.json there)")
        low, high = self.steps
        if not 1 <= low <= high:
            raise ValueError(f"takeover steps range must be 1 <= low <= high, got {self.steps}")

    def check(self) -> None:
        """Loads the checkpoint now (once per process), so that a bad one fails before any episode
        runs, with an error naming --takeover."""
        try:
            _harness_policy(self.checkpoint, self.execute_steps)
        except Exception as error:  # noqa: BLE001 - any load failure is this flag's
            raise ValueError(f"--takeover {self.checkpoint}: {error}") from error

    def start(self, rng: np.random.Generator) -> "PolicyTakeoverState":
        """A fresh takeover for one episode, drawing from `rng` (the model is loaded once per process)."""
        return PolicyTakeoverState(self, rng)


class PolicyTakeoverState:
    """The takeover of one episode: `apply(action, observation)` -> (applied action, disturbed?).

    While the policy drives, `observation` must hold what it reads: the two camera images, the state
    and the instruction."""

    def __init__(self, settings: PolicyTakeover, rng: np.random.Generator) -> None:
        self.settings = settings
        self.steps = int(rng.integers(settings.steps[0], settings.steps[1] + 1))
        self.policy = _harness_policy(settings.checkpoint, settings.execute_steps)
        self._policy_seed = int(rng.integers(2**31))
        self._queue: list[np.ndarray] = []
        self.driven = 0  # steps the policy drove
        self.handed_back = False
        self.reason = ""  # why it handed back: "steps" or "close"

    def apply(self, action: np.ndarray, observation: dict | None = None) -> tuple[np.ndarray, bool]:
        if self.handed_back:
            return action, False
        if self.driven == 0 and not self._queue:  # the episode's first step: checked once
            if observation is None or not _POLICY_READS <= observation.keys():
                raise ValueError("PolicyTakeover needs observation['static_rgb'], ['wrist_rgb'], ['state'] and "
                                 "['instruction'] (collect with cameras)")
            self.policy.reset(str(observation["instruction"]), self._policy_seed)
        if not self._queue:
            self._queue = list(np.asarray(self.policy.act(observation), dtype=np.float64))
        applied = self._queue.pop(0)
        if applied[6] <= 0.0:  # the policy closes the hand: the expert takes over before it does
            return self._hand_back("close", action)
        self.driven += 1
        if self.driven >= self.steps:
            self._hand_back("steps", applied)
        return applied, True

    def _hand_back(self, reason: str, action: np.ndarray) -> tuple[np.ndarray, bool]:
        self.handed_back, self.reason = True, reason
        if self.settings.expert is not None:
            self.settings.expert.replan()
        return action, False
