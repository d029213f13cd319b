"""The button's logic: each press toggles the lamp, which the plant then raises into view."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

# The cap counts as pressed below this joint position [m] (its travel is 0 to -0.015 m).
PRESS_THRESHOLD = -0.008
# It must come back above this before another press counts (hysteresis against chatter) [m].
RELEASE_THRESHOLD = -0.004
# The lamp's lift when lit [m]: its top then stands 1.4 cm above the housing.
LAMP_LIFT_ON = 0.015
LIT, PRESSED = 0, 1


class ButtonLampLogic(LeafSystem):
    """Latches the lamp state and outputs the button model's PD targets.

    Input `button_state` (4-vector: button_press [m], lamp_lift [m], their rates [m/s]).
    Output `desired_state` (4-vector, same layout): the cap's rest position 0 and the lamp's lift.
    Output `lamp_on` (1-vector, 0 or 1). Discrete state [lit, pressed], updated at `period_s`.
    """

    def __init__(self, period_s: float = 0.01, initially_lit: bool = False):
        super().__init__()
        self._state_port = self.DeclareVectorInputPort("button_state", 4)
        state_index = self.DeclareDiscreteState(np.array([float(initially_lit), 0.0]))
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        self.DeclareVectorOutputPort("desired_state", 4, self._calc_desired_state)
        self.DeclareVectorOutputPort("lamp_on", 1, self._calc_lamp_on)
        self._state_index = state_index

    def _update(self, context, discrete_state):
        lit, pressed = context.get_discrete_state(self._state_index).value()
        cap = self._state_port.Eval(context)[0]
        if not pressed and cap < PRESS_THRESHOLD:
            lit, pressed = 1.0 - lit, 1.0
        elif pressed and cap > RELEASE_THRESHOLD:
            pressed = 0.0
        discrete_state.get_mutable_vector(self._state_index).SetFromVector([lit, pressed])

    def _calc_desired_state(self, context, output: BasicVector):
        lit = context.get_discrete_state(self._state_index).value()[LIT]
        output.SetFromVector([0.0, LAMP_LIFT_ON * lit, 0.0, 0.0])

    def _calc_lamp_on(self, context, output: BasicVector):
        output.SetAtIndex(0, context.get_discrete_state(self._state_index).value()[LIT])

    def set_lit(self, context, lit: bool) -> None:
        """Set the latched lamp state in this system's context (for task initialisation)."""
        context.get_mutable_discrete_state(self._state_index).SetFromVector([float(lit), 0.0])
