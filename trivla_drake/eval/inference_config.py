"""`InferenceConfig`: how TriVLA's System 1 is sampled and its action chunks are played, shared by `demo`,
`evaluate` and `tables` (each None: the shipped default)."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc
from typing import Optional


@dc.dataclass
class InferenceConfig:
    """TriVLA's inference settings (other policies take none of them)."""

    # Standard deviation of the noise System 1's flow-matching sampling starts from (None: 1, the paper's;
    # 0: deterministic chunks).
    noise_scale: Optional[float] = None
    # Replan every this many control steps, playing the first rows of each chunk (None: the whole chunk, 10 steps,
    # as the Drake TriVLAPolicy's default).
    execute_steps: Optional[int] = None
    # ACT's temporal ensembling of the chunks that cover a step, weights exp(-m i) with i = 0 the oldest (None: play
    # the newest chunk). Useful with execute_steps below the chunk length, where chunks overlap.
    ensemble_decay: Optional[float] = None

    def is_default(self) -> bool:
        """True when no setting is given (every policy takes that)."""
        return self == InferenceConfig()

    def validate(self, prefix: str = "inference.", *, chunk_length: Optional[int] = None) -> None:
        """ValueError naming the dotted field (`prefix` + name) of a setting out of range; execute_steps is checked
        against `chunk_length` when given (else when the checkpoint loads)."""
        if self.noise_scale is not None:
            from trivla_drake.nn.policy import check_noise_scale

            check_noise_scale(self.noise_scale, f"{prefix}noise_scale")
        if self.execute_steps is not None:
            from trivla_drake.eval.trivla_harness_policy import check_execute_steps

            check_execute_steps(self.execute_steps, chunk_length, f"{prefix}execute_steps")
        if self.ensemble_decay is not None:
            from trivla_drake.eval.trivla_harness_policy import check_ensemble_decay

            check_ensemble_decay(self.ensemble_decay, f"{prefix}ensemble_decay")
