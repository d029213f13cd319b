"""How far the Panda's gripper is closed, from the robot state (the instruction grounding's phase input).

The state is laid out as the station's `panda.state` port: 7 arm joint angles [rad], then the two
finger positions [m] (each finger's travel from the centre, 0 to 0.04), then 9 velocities. The
gripper's closure is 0 with the fingers fully open and 1 with them touching; holding one of the
suite's blocks (4.5 cm across) it is about 0.44. It tells a stack instruction's two phases apart:
before the grasp the instruction names the block to pick up, while the block is held the block to put it
on (research/stack_phase).
"""

from __future__ import annotations

import torch

# Distance between the fingers fully open [m]: both at their 0.04 m limit (station/panda_driver.py's
# MAX_GRIPPER_WIDTH; that module builds Drake systems, which torch code does not import).
MAX_GRIPPER_WIDTH = 0.08
FINGER_STATE_INDICES = (7, 8)  # the finger positions' entries of the state
FEATURE_DIM = 1
# The closures at which a block is held: fingers 2-6 cm apart. The suite's blocks (4.5 cm) give 0.44; fully
# open gives 0, closed on nothing (a push, a button press) 1, and the drawer's 1.2 cm handle bar 0.85.
HELD_CLOSURE = (0.25, 0.75)


def gripper_closure(state: torch.Tensor) -> torch.Tensor:
    """Unnormalised robot states (B, >= 9) -> the gripper's closure (B, 1): 1 - width / 0.08, where
    width is the sum of the two finger positions [m]. Fully open gives 0."""
    if state.dim() != 2 or state.shape[1] <= max(FINGER_STATE_INDICES):
        raise ValueError(f"state must be (B, >= {max(FINGER_STATE_INDICES) + 1}) with the finger positions at "
                         f"{FINGER_STATE_INDICES}; got {tuple(state.shape)}")
    width = state[:, FINGER_STATE_INDICES[0]] + state[:, FINGER_STATE_INDICES[1]]
    return (1.0 - width / MAX_GRIPPER_WIDTH).unsqueeze(-1)


def holding_block(closure: torch.Tensor) -> torch.Tensor:
    """Closures (B, 1) -> bool (B,): whether the fingers are closed on a block (within HELD_CLOSURE)."""
    low, high = HELD_CLOSURE
    return ((closure >= low) & (closure <= high)).squeeze(-1)
