"""`PeriodicInferenceSystem`: the shared shape of TriVLA's three Drake systems.

A periodic unrestricted update runs one inference; its result, a small numpy payload, is stored
in the Context's abstract state (`InferenceSlots`) and published on one abstract output port when
the latency model says it is ready. The output is a function of the state and the time (a declared
prerequisite, so Drake's caching stays right): an event at each ready time would need a timed or
per-step event, where the readers (the next stage's periodic ticks) only ever look at tick times.
The network's weights stay on the system object, read-only: Drake deep-copies abstract state on
every update and on Context clones.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.sensors import ImageRgba8U

from trivla_drake.systems.latency import InferenceSlots, LatencyModel


class PeriodicInferenceSystem(LeafSystem):
    """Base class: subclasses declare their inputs and implement `infer(context, seed)`.

    Output `<output_name>`: the latest visible result (None before the first one).
    Output `<output_name>_stamp`: 1-vector, sim time [s] of the observation it was computed from
    (NaN before the first one). Numeric parameter `seed` (set with `set_seed`) seeds each inference
    together with the count of inferences so far, so rollouts are reproducible per Context.
    Inferences run at offset_s + n period_s [s] of sim time.
    """

    def __init__(self, *, period_s: float, latency: LatencyModel | None, output_name: str, seed: int = 0,
                 offset_s: float = 0.0):
        super().__init__()
        if not period_s > 0:
            raise ValueError(f"{type(self).__name__} period_s must be positive, got {period_s}")
        if not 0.0 <= offset_s < period_s:
            raise ValueError(f"{type(self).__name__} offset_s must be in [0, period_s = {period_s:g}), got {offset_s}")
        self._period_s = period_s
        self._latency = latency or LatencyModel()
        self._slots_index = self.DeclareAbstractState(AbstractValue.Make(InferenceSlots()))
        self._seed_index = self.DeclareNumericParameter(BasicVector([float(seed)]))
        self.DeclareInitializationUnrestrictedUpdateEvent(self._on_initialize)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, offset_s, self._on_tick)
        prerequisites = {self.time_ticket(), self.abstract_state_ticket(self._slots_index)}
        self.DeclareAbstractOutputPort(
            output_name, lambda: AbstractValue.Make(None), self._calc_visible, prerequisites
        )
        self.DeclareVectorOutputPort(
            f"{output_name}_stamp", 1, self._calc_stamp, prerequisites_of_calc=prerequisites
        )

    @property
    def period_s(self) -> float:
        return self._period_s

    def set_seed(self, context, seed: int) -> None:
        """Seed this system's inferences in `context` (its own or the root's subcontext)."""
        context.get_mutable_numeric_parameter(self._seed_index).SetAtIndex(0, float(seed))

    def slots(self, context) -> InferenceSlots:
        """The published and in-flight results in `context`."""
        return context.get_abstract_state(self._slots_index).get_value()

    # Subclasses implement these two.
    def check_inputs(self, context) -> None:
        """Raise ValueError naming a port that is unconnected or carries a wrong-sized value."""

    def infer(self, context, seed: int) -> Any:
        """One inference on the inputs at the context's time; None means "not ready, skip"."""
        raise NotImplementedError

    def _on_initialize(self, context, state):
        self.check_inputs(context)
        state.get_mutable_abstract_state(self._slots_index).set_value(InferenceSlots())

    def _on_tick(self, context, state):
        t = context.get_time()
        slots = self.slots(context).settle(t)
        if not slots.busy(t):
            base_seed = int(context.get_numeric_parameter(self._seed_index).GetAtIndex(0))
            start = time.perf_counter()
            value = self.infer(context, seed=base_seed * 1_000_003 + slots.count)
            wall = time.perf_counter() - start
            if value is not None:
                slots = slots.start(t, value, self._latency.delay(wall))
                slots = slots.settle(t)  # zero delay: visible at once
        state.get_mutable_abstract_state(self._slots_index).set_value(slots)

    def _calc_visible(self, context, output):
        output.set_value(self.slots(context).visible(context.get_time())[0])

    def _calc_stamp(self, context, output: BasicVector):
        output.SetAtIndex(0, self.slots(context).visible(context.get_time())[1])


def declare_image_input(system: LeafSystem, name: str):
    """An ImageRgba8U input port (colour image straight from an RgbdSensor)."""
    return system.DeclareAbstractInputPort(name, AbstractValue.Make(ImageRgba8U()))


def read_rgb(port, context, size: int) -> np.ndarray:
    """The image on `port` as uint8 (size, size, 3); ValueError naming the port if it is not that."""
    if not port.HasValue(context):
        raise ValueError(f"input port '{port.get_name()}' is not connected (an ImageRgba8U {size}x{size} is needed)")
    image = port.Eval(context)
    if image.width() == 0 or image.height() == 0:
        raise ValueError(f"input port '{port.get_name()}' carries no image (0x0): is it connected to a camera?")
    if (image.width(), image.height()) != (size, size):
        raise ValueError(
            f"input port '{port.get_name()}' carries a {image.width()}x{image.height()} image; "
            f"the model needs {size}x{size}"
        )
    return np.ascontiguousarray(image.data[:, :, :3])


def read_instruction(port, context) -> str:
    """The instruction string on `port`; ValueError naming the port if unconnected or not a str."""
    if not port.HasValue(context):
        raise ValueError(f"input port '{port.get_name()}' is not connected (an instruction string is needed)")
    value = port.Eval(context)
    if not isinstance(value, str):
        raise ValueError(f"input port '{port.get_name()}' must carry a str, got {type(value).__name__}")
    return value
