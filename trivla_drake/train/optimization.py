"""AdamW with its parameter groups, and the learning-rate schedule (warm-up, then a cosine)."""

from __future__ import annotations

import math

import torch
from torch import nn

from trivla_drake.train.config import TrainConfig


def learning_rate(config: TrainConfig, step: int) -> float:
    """Linear warm-up to `lr` (over warmup_steps, at most a tenth of the run), then a cosine down to
    lr * min_lr_ratio at `steps`."""
    warmup = min(config.optimizer.warmup_steps, max(1, config.steps // 10))
    if step < warmup:
        return config.lr * (step + 1) / warmup
    span = max(1, config.steps - warmup)
    progress = min(1.0, (step - warmup) / span)
    return config.lr * (config.optimizer.min_lr_ratio + (1 - config.optimizer.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress)))


def make_optimizer(module: nn.Module, config: TrainConfig) -> torch.optim.Optimizer:
    """AdamW; matrices decay, vectors do not, nor the parameters a module names in its NO_WEIGHT_DECAY
    (positions, such as the grounding anchor's places, which decay would pull toward the origin); in a
    joint run System 1's instruction grounding learns at `grounding_lr_scale` times the run's learning
    rate (each group's "lr_scale")."""
    scaled = config.policy.grounding.phase == "joint"
    undecayed = {f"{prefix}.{name}" if prefix else name
                 for prefix, sub in module.named_modules() for name in getattr(sub, "NO_WEIGHT_DECAY", ())}
    groups: dict[tuple[bool, bool], list[nn.Parameter]] = {}
    for name, p in module.named_parameters():
        if p.requires_grad:
            decay = p.dim() >= 2 and name not in undecayed
            groups.setdefault((decay, scaled and name.startswith("grounding.")), []).append(p)
    return torch.optim.AdamW(
        [{"params": params, "weight_decay": config.optimizer.weight_decay if decay else 0.0,
          "lr_scale": config.policy.grounding.lr_scale if grounding else 1.0}
         for (decay, grounding), params in sorted(groups.items(), key=lambda kv: (not kv[0][0], kv[0][1]))],
        lr=config.lr, betas=(config.optimizer.beta1, config.optimizer.beta2),
    )
