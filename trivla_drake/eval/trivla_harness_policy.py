"""TriVLA as a policy of the evaluation harness (plain Python: one chunk per call, no Drake systems).

The harness executes the returned (10, 7) chunk one row per control step, then asks again: the
same replanning every 10 steps as the Drake `TriVLAPolicy`, without simulated latency.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trivla_drake.nn import TriVLA, load_checkpoint


class TriVLAHarnessPolicy:
    """Wraps a TriVLA model in the harness's Policy protocol (reset / act)."""

    name = "trivla"
    uses_images = True
    privileged = False

    def __init__(self, model: TriVLA, *, name: str | None = None):
        self.model = model.eval()
        if name:
            self.name = name
        self._instruction = ""
        self._seed = 0
        self._calls = 0

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> "TriVLAHarnessPolicy":
        return cls(load_checkpoint(str(path)), name=f"trivla:{Path(path).name}")

    def reset(self, instruction: str, seed: int) -> None:
        self._instruction, self._seed, self._calls = instruction, int(seed), 0

    def act(self, observation: dict) -> np.ndarray:
        self._calls += 1
        return self.model.predict_action_chunk(
            {
                "static_rgb": observation["static_rgb"],
                "wrist_rgb": observation["wrist_rgb"],
                "instruction": self._instruction,
                "state": observation["state"],
                "embodiment_id": 0,
            },
            seed=self._seed * 100_003 + self._calls,
        )
