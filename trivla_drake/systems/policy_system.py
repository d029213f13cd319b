"""System 1 as a Drake system: Q_vl, Q_p and the robot state -> a flow-matching action chunk."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.periodic_inference import PeriodicInferenceSystem

N_STATE = 18


class PolicySystem(PeriodicInferenceSystem):
    """TriVLA's System 1 (diffusion transformer sampled by Euler flow-matching steps).

    Inputs: `q_vl` (System 2's output; unused when the model has no System 2), `q_p` (System 3's
    output; unused without System 3), `robot_state` (18-vector: Panda q (7 arm [rad], 2 fingers [m])
    then v [rad/s, m/s]).
    Output `action_chunk`: float32 numpy (action_horizon, 7), 10 for the presets, of relative
    end-effector actions (see
    trivla_drake.tasks action space), `action_chunk_stamp`: sim time [s] of the state it used.
    It waits (skips its tick) until the systems it needs have published once.
    """

    def __init__(self, model: TriVLA, *, period_s: float, latency: LatencyModel | None = None, seed: int = 0,
                 offset_s: float = 0.0):
        super().__init__(period_s=period_s, latency=latency, output_name="action_chunk", seed=seed,
                         offset_s=offset_s)
        self._model = model
        self._q_vl = self.DeclareAbstractInputPort("q_vl", AbstractValue.Make(None))
        self._q_p = self.DeclareAbstractInputPort("q_p", AbstractValue.Make(None))
        self._state = self.DeclareVectorInputPort("robot_state", N_STATE)

    def _optional(self, port, context, needed: bool, what: str):
        if not needed:
            return None
        if not port.HasValue(context):
            raise ValueError(f"input port '{port.get_name()}' is not connected but the model uses {what}")
        return port.Eval(context)

    def check_inputs(self, context) -> None:
        self._optional(self._q_vl, context, self._model.vision_language is not None, "System 2")
        self._optional(self._q_p, context, self._model.dynamics is not None, "System 3")
        if not self._state.HasValue(context):
            raise ValueError("input port 'robot_state' is not connected (an 18-vector is needed)")

    def infer(self, context, seed: int):
        q_vl = self._optional(self._q_vl, context, self._model.vision_language is not None, "System 2")
        q_p = self._optional(self._q_p, context, self._model.dynamics is not None, "System 3")
        if (self._model.vision_language is not None and q_vl is None) or (
            self._model.dynamics is not None and q_p is None
        ):
            return None  # the slower systems have not published yet
        state = np.asarray(self._state.Eval(context))
        q_s = self._model.encode_state(state)
        return self._model.sample_actions(q_vl, q_s, q_p, seed=seed, state=state)
