"""The Policy protocol the episode runner drives, the random baseline, and `load_policy`.

A policy is reset with the instruction at the start of every (sub)task and then asked for actions:

    policy.reset(instruction, seed)
    action = policy.act(observation)   # (7,) one step, or (k, 7) a chunk executed step by step

Actions are defined in `trivla_drake.action` (relative end-effector pose change
in the world frame + gripper). The observation is the dict of `trivla_drake.eval.env` plus
`instruction`; policies with `privileged = True` (the oracle) also get `privileged`:
{"scene": SceneState, "task": TaskInstance}. `uses_images = False` lets the runner skip rendering.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from trivla_drake.systems.action_executor import ACTION_DIM, ACTION_HIGH, ACTION_LOW

POLICY_CHOICES = ("oracle", "random", "trivla")


@runtime_checkable
class Policy(Protocol):
    """What the evaluation harness and the data collector drive."""

    name: str
    uses_images: bool
    privileged: bool

    def reset(self, instruction: str, seed: int) -> None:
        """Start a new (sub)task; all randomness from here on comes from `seed`."""

    def act(self, observation: dict) -> np.ndarray:
        """Action (7,) for this step, or a chunk (k, 7) to execute one row per control step."""


class RandomPolicy:
    """Uniform random actions inside the action bounds, each held for `hold_steps` steps (so the arm
    actually wanders instead of jittering in place), random gripper command."""

    name = "random"
    uses_images = False
    privileged = False

    def __init__(self, hold_steps: int = 12):
        if hold_steps < 1:
            raise ValueError(f"hold_steps must be at least 1, got {hold_steps}")
        self._hold_steps = hold_steps
        self._rng = np.random.default_rng(0)

    def reset(self, instruction: str, seed: int) -> None:
        self._rng = np.random.default_rng(seed)

    def act(self, observation: dict) -> np.ndarray:
        action = self._rng.uniform(ACTION_LOW, ACTION_HIGH)
        action[6] = 1.0 if action[6] > 0 else -1.0
        return np.tile(action, (self._hold_steps, 1))


def load_checkpoint_policy(
    path: str | Path,
    noise_scale: float | None = None,
    *,
    execute_steps: int | None = None,
    ensemble_decay: float | None = None,
) -> Policy:
    """A learned TriVLA policy from a checkpoint directory (see trivla_harness_policy.py); `noise_scale`
    sets the standard deviation of the noise System 1's sampling starts from (default 1);
    `execute_steps` K replans every K steps (default: the whole chunk); `ensemble_decay` m averages
    the chunks covering each step (ACT's temporal ensembling; default: play the newest)."""
    from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy

    policy = TriVLAHarnessPolicy.from_checkpoint(path, execute_steps=execute_steps, ensemble_decay=ensemble_decay)
    if noise_scale is not None:
        policy.model.set_initial_noise_scale(noise_scale)
    return policy


def load_policy(
    spec: str,
    noise_scale: float | None = None,
    *,
    execute_steps: int | None = None,
    ensemble_decay: float | None = None,
) -> Policy:
    """'oracle', 'random', 'trivla' (the shipped checkpoint, models/trivla_cpu), or a checkpoint directory.
    `noise_scale`, `execute_steps`, `ensemble_decay` (TriVLA only): see load_checkpoint_policy."""
    for field, value in (("inference.noise_scale", noise_scale), ("inference.execute_steps", execute_steps),
                         ("inference.ensemble_decay", ensemble_decay)):
        if value is not None and spec in ("oracle", "random"):
            raise ValueError(f"{field} applies to TriVLA checkpoints only, not to --policy {spec}")
    settings = dict(execute_steps=execute_steps, ensemble_decay=ensemble_decay)
    if spec == "trivla":
        from trivla_drake.eval.model_loading import default_checkpoint_dir

        default = default_checkpoint_dir()
        if not (default / "config.json").exists():
            raise ValueError(f"--policy trivla needs the shipped checkpoint at {default}; it is missing "
                             "(give a checkpoint directory instead)")
        return load_checkpoint_policy(default, noise_scale, **settings)
    if spec == "oracle":
        from trivla_drake.tasks.oracle import OraclePolicy

        return OraclePolicy()
    if spec == "random":
        return RandomPolicy()
    path = Path(spec)
    if not path.exists():
        raise ValueError(
            f"--policy {spec!r} is neither one of {', '.join(POLICY_CHOICES)} nor an existing checkpoint path"
        )
    return load_checkpoint_policy(path, noise_scale, **settings)


def as_action_rows(output, name: str = "policy output") -> np.ndarray:
    """A policy's output as (k, 7) float rows; ValueError naming the problem otherwise."""
    array = np.asarray(output, dtype=float)
    if array.ndim == 1:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != ACTION_DIM or array.shape[0] == 0:
        raise ValueError(f"{name} must have shape (7,) or (k, 7), got {np.shape(output)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} has NaN or infinite entries")
    return array
