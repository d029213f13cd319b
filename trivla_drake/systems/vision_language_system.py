"""System 2 as a Drake system: camera images + instruction -> Q_vl, at its own (slow) rate."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.periodic_inference import (
    PeriodicInferenceSystem,
    declare_image_input,
    read_instruction,
    read_rgb,
)

N_STATE = 18


class VisionLanguageSystem(PeriodicInferenceSystem):
    """TriVLA's System 2 (Eagle-2 style VLM read out at a middle LLM layer).

    Inputs: `static_rgb`, `wrist_rgb` (ImageRgba8U, model size, e.g. 224x224), `instruction` (str),
    `robot_state` (18-vector: Panda q then v [rad, m, rad/s, m/s]).
    Output `q_vl`: float32 numpy (tokens, LLM width), the middle-layer hidden states;
    `q_vl_stamp`: sim time [s] of the images it saw. The instruction is read at every update,
    so a new one takes effect at the next System 2 tick.
    """

    def __init__(self, model: TriVLA, *, period_s: float, latency: LatencyModel | None = None, seed: int = 0,
                 offset_s: float = 0.0):
        if model.vision_language is None:
            raise ValueError("VisionLanguageSystem needs a model with System 2 (config.use_system2 = True)")
        super().__init__(period_s=period_s, latency=latency, output_name="q_vl", seed=seed,
                         offset_s=offset_s)
        self._model = model
        self._static = declare_image_input(self, "static_rgb")
        self._wrist = declare_image_input(self, "wrist_rgb")
        self._instruction = self.DeclareAbstractInputPort("instruction", AbstractValue.Make(""))
        self._state = self.DeclareVectorInputPort("robot_state", N_STATE)

    def check_inputs(self, context) -> None:
        size = self._model.image_size
        read_rgb(self._static, context, size)
        read_rgb(self._wrist, context, size)
        read_instruction(self._instruction, context)

    def infer(self, context, seed: int) -> np.ndarray:
        size = self._model.image_size
        q_vl, _ = self._model.encode_vision_language(
            read_rgb(self._static, context, size),
            read_rgb(self._wrist, context, size),
            read_instruction(self._instruction, context),
            np.asarray(self._state.Eval(context)),
        )
        return q_vl


