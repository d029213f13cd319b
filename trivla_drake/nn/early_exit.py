"""Run a module's forward only up to a chosen sub-module, recording the outputs of some sub-modules.

Both read-outs of the paper stop early: System 2 takes a middle LLM layer (layers above it never run)
and System 3 takes the first up-sampling blocks of the video UNet (later blocks and conv_out never
run). Forward hooks record outputs and a private exception unwinds the call after the last one needed,
so the libraries' own forward code (masks, embeddings, skip connections) is reused unchanged.
Not thread-safe for concurrent calls on one module (hooks are per-module).
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import nn


class _StopForward(Exception):
    """Raised by the hook on the last needed sub-module to abandon the rest of the forward pass."""


def _first_tensor(output: object) -> torch.Tensor:
    if isinstance(output, torch.Tensor):
        return output
    if isinstance(output, (tuple, list)) and output and isinstance(output[0], torch.Tensor):
        return output[0]
    raise TypeError(f"cannot take a tensor from a sub-module output of type {type(output).__name__}")


def run_until(
    call: Callable[[], object], capture: Sequence[nn.Module], stop_after: nn.Module
) -> list[torch.Tensor]:
    """Calls `call()`, returns the outputs of the `capture` modules (in order), and aborts the call as soon
    as `stop_after` has produced its output. Raises RuntimeError if `stop_after` never ran."""
    outputs: dict[int, torch.Tensor] = {}
    handles = []

    def make_hook(index: int, stop: bool):
        def hook(module: nn.Module, args: object, output: object) -> None:
            outputs[index] = _first_tensor(output)
            if stop:
                raise _StopForward

        return hook

    try:
        for i, module in enumerate(capture):
            handles.append(module.register_forward_hook(make_hook(i, module is stop_after)))
        if not any(m is stop_after for m in capture):
            handles.append(stop_after.register_forward_hook(make_hook(len(capture), True)))
        try:
            call()
        except _StopForward:
            pass
        else:
            raise RuntimeError("run_until: the stop module did not run during the call")
    finally:
        for handle in handles:
            handle.remove()
    missing = [i for i in range(len(capture)) if i not in outputs]
    if missing:
        raise RuntimeError(f"run_until: captured modules {missing} did not run before the stop module")
    return [outputs[i] for i in range(len(capture))]
