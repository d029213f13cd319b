"""TriVLA as a policy of the evaluation harness (plain Python: one chunk per call, no Drake systems).

The harness executes the returned rows one per control step, then asks again. By default each call
returns System 1's whole (10, 7) chunk: the same replanning every 10 steps as the Drake
`TriVLAPolicy`, without simulated latency. With `execute_steps` K the model replans every K steps
(only the first K rows of each chunk are played), and with `ensemble_decay` m every step's action is
ACT's temporal ensemble of the chunks that cover it (weight exp(-m i), i = 0 the oldest): the
harness's counterpart of `PolicyRates.replanning_every(K, ensemble_decay=m)`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trivla_drake.nn import TriVLA, load_checkpoint
from trivla_drake.nn.policy import check_noise_scale
from trivla_drake.systems.action_chunk_executor import ChunkHistory, covering_chunks, select_action


def check_execute_steps(steps, horizon: int | None, field: str = "execute_steps") -> int:
    """`steps` as an int; ValueError naming `field` unless 1 <= steps <= horizon (the chunk length; None:
    no upper bound)."""
    bound = f"from 1 to the chunk length {horizon}" if horizon is not None else ">= 1"
    if (isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1
            or (horizon is not None and steps > horizon)):
        raise ValueError(f"{field} must be an integer {bound}, got {steps!r}")
    return int(steps)


def check_ensemble_decay(decay, field: str = "ensemble_decay") -> float:
    """`decay` as a float; ValueError naming `field` unless it is a finite number >= 0."""
    try:
        return check_noise_scale(decay, field)  # the same bounds: a finite number >= 0
    except (TypeError, ValueError):
        raise ValueError(f"{field} must be a finite number >= 0, got {decay!r}") from None


class TriVLAHarnessPolicy:
    """Wraps a TriVLA model in the harness's Policy protocol (reset / act)."""

    name = "trivla"
    uses_images = True
    privileged = False

    def __init__(
        self,
        model: TriVLA,
        *,
        name: str | None = None,
        execute_steps: int | None = None,
        ensemble_decay: float | None = None,
    ):
        self.model = model.eval()
        if name:
            self.name = name
        horizon = int(model.config.policy.action_horizon)
        self.execute_steps = horizon if execute_steps is None else check_execute_steps(
            execute_steps, horizon, "execute_steps")
        self.ensemble_decay = None if ensemble_decay is None else check_ensemble_decay(ensemble_decay)
        self._keep = covering_chunks(horizon, self.execute_steps) if self.ensemble_decay is not None else 1
        self._instruction = ""
        self._seed = 0
        self._calls = 0
        self._step = 0
        self._history = ChunkHistory()

    @classmethod
    def from_checkpoint(
        cls, path: str | Path, *, execute_steps: int | None = None, ensemble_decay: float | None = None
    ) -> "TriVLAHarnessPolicy":
        return cls(load_checkpoint(str(path)), name=f"trivla:{Path(path).name}", execute_steps=execute_steps,
                   ensemble_decay=ensemble_decay)

    def reset(self, instruction: str, seed: int) -> None:
        self._instruction, self._seed, self._calls = instruction, int(seed), 0
        self._step, self._history = 0, ChunkHistory()

    def act(self, observation: dict) -> np.ndarray:
        """The actions of the next `execute_steps` control steps, (K, 7)."""
        self._calls += 1
        chunk = self.model.predict_action_chunk(
            {
                "static_rgb": observation["static_rgb"],
                "wrist_rgb": observation["wrist_rgb"],
                "instruction": self._instruction,
                "state": observation["state"],
                "embodiment_id": 0,
            },
            seed=self._seed * 100_003 + self._calls,
        )
        if self.ensemble_decay is None:
            self._step += self.execute_steps
            return chunk[: self.execute_steps]
        # Time in control steps: the chunk observed at step s holds the actions of s, s + 1, ...
        self._history = self._history.add(float(self._step), chunk, self._keep)
        rows = [select_action(self._history, float(self._step + k), 1.0, self.ensemble_decay)
                for k in range(self.execute_steps)]
        self._step += self.execute_steps
        return np.stack(rows).astype(np.float32)
