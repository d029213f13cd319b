"""Sub-goal labels of a demonstration: where the tool-centre point is when the gripper next changes.

A language-conditioned task names one object among several ("the red block"). The place where the
expert next closes or opens the gripper is the named object (a grasp) or the named destination (a
release); past the last change it is where the episode ends (a push's end, a drawer's handle).
System 1's instruction grounding (`nn/instruction_grounding.py`) learns to predict it from the
instruction and the images, a dense training signal for *which* object the words name. Labels only:
nothing here is an input at inference.

Only the *approach* frames, those before the first gripper change, train the grounding: there the
named object is the only cue to the sub-goal. Once a block is held, the wrist view shows the
answer, and with those frames in the loss the grounding never learnt to read the colour word (10 of
30 queries nearest the named block, chance; 28 of 30 on the approach frames alone,
results/instruction_grounding).
"""

from __future__ import annotations

import numpy as np


def gripper_changes(gripper: np.ndarray) -> np.ndarray:
    """Frames k whose gripper command (T,) has another sign than frame k-1's, ascending."""
    return np.flatnonzero(np.sign(gripper[1:]) != np.sign(gripper[:-1])) + 1


def approach_frames(gripper: np.ndarray) -> np.ndarray:
    """bool (T,): True for the frames before the first gripper change (every frame when there is none)."""
    gripper = np.asarray(gripper, dtype=np.float64)
    if gripper.ndim != 1:
        raise ValueError(f"gripper must be (T,); got {gripper.shape}")
    changes = gripper_changes(gripper)
    first = int(changes[0]) if changes.size else len(gripper)
    return np.arange(len(gripper)) < first


def next_gripper_event_positions(gripper: np.ndarray, tcp_position: np.ndarray) -> np.ndarray:
    """Per frame t of an episode, the tool-centre-point position at the first frame k > t whose
    gripper command has another sign than frame k-1's, else at the last frame.

    gripper (T,) commands (sign: open / closed); tcp_position (T, 3) [m]. Returns float32 (T, 3)."""
    gripper = np.asarray(gripper, dtype=np.float64)
    tcp_position = np.asarray(tcp_position, dtype=np.float64)
    if gripper.ndim != 1 or tcp_position.shape != (len(gripper), 3):
        raise ValueError(
            f"gripper must be (T,) and tcp_position (T, 3); got {gripper.shape} and {tcp_position.shape}"
        )
    length = len(gripper)
    if length == 0:
        return np.zeros((0, 3), dtype=np.float32)
    if not (np.isfinite(gripper).all() and np.isfinite(tcp_position).all()):
        raise ValueError("gripper and tcp_position must be finite")
    events = np.append(gripper_changes(gripper), length - 1)
    # For frame t: the first event index strictly after t (the last frame when none is left).
    which = np.searchsorted(events, np.arange(length), side="right")
    return tcp_position[events[np.minimum(which, len(events) - 1)]].astype(np.float32)
