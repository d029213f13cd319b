"""System 3 as a Drake system: one UNet pass per view -> the dynamics features F_p."""

from __future__ import annotations

from pydrake.common.value import AbstractValue

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.periodic_inference import (
    PeriodicInferenceSystem,
    declare_image_input,
    read_instruction,
    read_rgb,
)


class DynamicsPerceptionSystem(PeriodicInferenceSystem):
    """TriVLA's System 3 (SVD-style spatio-temporal UNet, ONE forward pass per view).

    Inputs: `static_rgb`, `wrist_rgb` (ImageRgba8U, model size), `instruction` (str).
    Output `q_p`: dict {"static", "wrist"} of float32 numpy (frames, channels, H_p, W_p), the
    up-sampling features resized and concatenated (eq. 2-3); `q_p_stamp`: sim time [s] of the images.
    """

    def __init__(self, model: TriVLA, *, period_s: float, latency: LatencyModel | None = None, seed: int = 0,
                 offset_s: float = 0.0):
        if model.dynamics is None:
            raise ValueError("DynamicsPerceptionSystem needs a model with System 3 (config.use_system3 = True)")
        super().__init__(period_s=period_s, latency=latency, output_name="q_p", seed=seed,
                         offset_s=offset_s)
        self._model = model
        self._static = declare_image_input(self, "static_rgb")
        self._wrist = declare_image_input(self, "wrist_rgb")
        self._instruction = self.DeclareAbstractInputPort("instruction", AbstractValue.Make(""))

    def check_inputs(self, context) -> None:
        size = self._model.image_size
        read_rgb(self._static, context, size)
        read_rgb(self._wrist, context, size)
        read_instruction(self._instruction, context)

    def infer(self, context, seed: int) -> dict:
        size = self._model.image_size
        return self._model.encode_dynamics(
            read_rgb(self._static, context, size),
            read_rgb(self._wrist, context, size),
            read_instruction(self._instruction, context),
            seed=seed,
        )
