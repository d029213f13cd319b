"""System 3 on a batch whose frames all share one instruction (the feature cache runs one episode at a time), with
the instruction's work done once instead of once per frame and latent position.

SVD's UNet repeats the text conditioning for every frame of every clip (and, in its temporal blocks, for every
latent position), and each cross-attention projects those copies to keys and values: with one instruction per batch
that is the same projection computed B * (T+1) or B * h * w times, about a third of System 3's work for the `cpu`
preset. Inside `shared_instruction(dynamics)`:
- every cross-attention of the UNet whose context rows are all equal (checked, `torch.equal`) projects one row to
  keys and values, used by every row of the batch (`SharedContextAttnProcessor`); any other call (mixed
  instructions, masks, normalisations this does not handle) takes the processor it had;
- the CLIP text encoder (when System 3 has one) runs on one copy of a batch of equal token rows.
Outputs are bit-identical to the plain path (tests/test_feature_cache_speed.py): the same projections of the same
rows, and the attention called as before. (Attending all the batch's queries in one call would be faster still,
but sums in another order: 3e-6 off on the tiny preset.) Not thread-safe for one module used by two threads at
once (it swaps processors and hooks on the module); the feature cache gives each worker thread its own copy.
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator

import torch
import torch.nn.functional as F
from torch import nn


def _all_rows_equal(x: torch.Tensor) -> bool:
    """True when every entry along dim 0 equals the first (and there is more than one)."""
    return x.shape[0] > 1 and (x.stride(0) == 0 or torch.equal(x, x[:1].expand_as(x)))


class SharedContextAttnProcessor:
    """A diffusers attention processor for cross-attention over one shared context: keys and values projected from
    the first context row only (AttnProcessor2_0's arithmetic otherwise). Calls it does not cover go to `fallback`
    (the module's own processor)."""

    def __init__(self, fallback: Any) -> None:
        self.fallback = fallback
        self.shared_calls = 0  # how many calls took the shared path (for tests and profiles)

    def _covers(self, attn: nn.Module, hidden_states: torch.Tensor, context: torch.Tensor | None,
                attention_mask: torch.Tensor | None, extra: bool) -> bool:
        return (context is not None and not extra and attention_mask is None and hidden_states.ndim == 3
                and attn.spatial_norm is None and attn.group_norm is None and not attn.norm_cross
                and attn.norm_q is None and attn.norm_k is None and _all_rows_equal(context))

    def __call__(self, attn: nn.Module, hidden_states: torch.Tensor, encoder_hidden_states: torch.Tensor | None = None,
                 attention_mask: torch.Tensor | None = None, temb: torch.Tensor | None = None, *args: Any,
                 **kwargs: Any) -> torch.Tensor:
        context = encoder_hidden_states
        if not self._covers(attn, hidden_states, context, attention_mask, bool(args or kwargs)):
            return self.fallback(attn, hidden_states, context, attention_mask, temb, *args, **kwargs)
        self.shared_calls += 1
        residual = hidden_states
        batch = hidden_states.shape[0]
        query = attn.to_q(hidden_states)
        # One row's keys and values, expanded (not copied) over the batch. The attention itself stays one call
        # over the batch as the library makes it: all queries in one block would sum in another order.
        key = attn.to_k(context[:1]).expand(batch, -1, -1)
        value = attn.to_v(context[:1]).expand(batch, -1, -1)
        inner = key.shape[-1]
        head = inner // attn.heads
        q = query.view(batch, -1, attn.heads, head).transpose(1, 2)
        k = key.reshape(batch, -1, attn.heads, head).transpose(1, 2)
        v = value.reshape(batch, -1, attn.heads, head).transpose(1, 2)
        out = F.scaled_dot_product_attention(q, k, v, dropout_p=0.0, is_causal=False)
        out = out.transpose(1, 2).reshape(batch, -1, inner).to(query.dtype)
        out = attn.to_out[1](attn.to_out[0](out))
        if attn.residual_connection:
            out = out + residual
        return out / attn.rescale_output_factor


def _cross_attentions(unet: nn.Module) -> list[nn.Module]:
    from diffusers.models.attention_processor import Attention

    return [m for m in unet.modules() if isinstance(m, Attention) and m.is_cross_attention]


@contextlib.contextmanager
def _text_encoded_once(text_encoder: nn.Module) -> Iterator[None]:
    """While inside: `text_encoder(input_ids=ids)` with all rows of `ids` equal runs on the first row, and every
    tensor of its output is expanded back to the batch."""
    rows: list[int] = []

    def before(module: nn.Module, args: tuple, kwargs: dict) -> tuple[tuple, dict] | None:
        ids = kwargs.get("input_ids")
        if args or ids is None or not _all_rows_equal(ids):
            rows.append(0)
            return None
        rows.append(ids.shape[0])
        return args, {**kwargs, "input_ids": ids[:1]}

    def after(module: nn.Module, args: tuple, kwargs: dict, output: Any) -> Any:
        batch = rows.pop()
        if not batch:
            return output

        def widen(value: Any) -> Any:
            if torch.is_tensor(value) and value.shape[:1] == (1,):
                return value.expand(batch, *value.shape[1:])
            return value

        if isinstance(output, tuple):
            return type(output)(widen(value) for value in output)
        for key, value in list(output.items()):  # a transformers ModelOutput
            output[key] = widen(value)
        return output

    handles = [text_encoder.register_forward_pre_hook(before, with_kwargs=True),
               text_encoder.register_forward_hook(after, with_kwargs=True)]
    try:
        yield
    finally:
        for handle in handles:
            handle.remove()


@contextlib.contextmanager
def shared_instruction(dynamics: nn.Module | None) -> Iterator[list[SharedContextAttnProcessor]]:
    """While inside, System 3 (`DynamicsPerceptionModule`, or None: nothing changes) computes the work of a batch's
    one instruction once (module doc); yields the installed processors. Everything is restored on exit."""
    if dynamics is None:
        yield []
        return
    attentions = _cross_attentions(dynamics.unet)
    previous = [m.processor for m in attentions]
    if any(isinstance(p, SharedContextAttnProcessor) for p in previous):  # already inside one: nothing to add
        yield [p for p in previous if isinstance(p, SharedContextAttnProcessor)]
        return
    installed = [SharedContextAttnProcessor(p) for p in previous]
    text_encoder = getattr(dynamics, "text_encoder", None)
    try:
        for module, processor in zip(attentions, installed):
            module.set_processor(processor)
        with _text_encoded_once(text_encoder) if text_encoder is not None else contextlib.nullcontext():
            yield installed
    finally:
        for module, processor in zip(attentions, previous):
            module.set_processor(processor)
