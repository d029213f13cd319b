"""Diagnostic (results/deeper_system1): an --init checkpoint like SRC with System 1's DiT deepened to
DEPTH blocks (the first blocks and every other weight copied, the new blocks fresh).

Usage: python deepen_system1.py SRC OUT DEPTH
"""

import dataclasses
import sys

import torch

from trivla_drake.nn.checkpoint import load_checkpoint, save_checkpoint
from trivla_drake.nn.trivla import TriVLA

src, out, depth = sys.argv[1], sys.argv[2], int(sys.argv[3])
model = load_checkpoint(src)
config = dataclasses.replace(model.config, policy=dataclasses.replace(model.config.policy, num_layers=depth))
torch.manual_seed(7)
deep = TriVLA(config)
weights = deep.state_dict()
for name, value in model.state_dict().items():
    if name not in weights or weights[name].shape != value.shape:
        raise ValueError(f"{name} does not fit the deepened model")
    weights[name] = value
deep.load_state_dict(weights)
print(f"System 1: {sum(p.numel() for p in model.policy.parameters()) / 1e6:.2f} M -> "
      f"{sum(p.numel() for p in deep.policy.parameters()) / 1e6:.2f} M parameters")
save_checkpoint(deep, out)
