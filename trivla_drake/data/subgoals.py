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
research/instruction_grounding). Optionally (`policy.grounding.carry_tasks`) the frames that carry a held
block to a destination the instruction names train it too (`carry_frames`): the wrist view shows the
block held, not where it goes, and nothing else asks for stack's second colour (research/stack_destinations).
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


def carry_frames(gripper: np.ndarray) -> np.ndarray:
    """bool (T,): True for the frames that carry a held object to its release: from the last close before
    the episode's last opening up to (not including) that opening. Their sub-goal label is the release
    position (`next_gripper_event_positions`). A grasp that missed and was opened again, before the final
    grasp, is not a carry. All False when the hand never opens after closing (a lift, a push)."""
    gripper = np.asarray(gripper, dtype=np.float64)
    if gripper.ndim != 1:
        raise ValueError(f"gripper must be (T,); got {gripper.shape}")
    carry = np.zeros(len(gripper), dtype=bool)
    changes = gripper_changes(gripper)
    openings = [int(k) for k in changes if gripper[k] > 0]
    closes = [int(k) for k in changes if gripper[k] <= 0]
    if openings:
        release = openings[-1]
        before = [k for k in closes if k < release]
        if before:
            carry[before[-1] : release] = True
    return carry


def next_gripper_event_frames(gripper: np.ndarray) -> np.ndarray:
    """Per frame t of an episode, the first frame k > t whose gripper command (T,) has another sign
    than frame k-1's, else the last frame. Returns int64 (T,)."""
    gripper = np.asarray(gripper, dtype=np.float64)
    length = len(gripper)
    events = np.append(gripper_changes(gripper), length - 1)
    # For frame t: the first event index strictly after t (the last frame when none is left).
    which = np.searchsorted(events, np.arange(length), side="right")
    return events[np.minimum(which, len(events) - 1)].astype(np.int64)


def _checked(gripper, values, name: str, width: int) -> tuple[np.ndarray, np.ndarray]:
    """gripper (T,) and per-frame `values` (T, width) as float64, after checking shapes and finiteness."""
    gripper = np.asarray(gripper, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if gripper.ndim != 1 or values.shape != (len(gripper), width):
        raise ValueError(f"gripper must be (T,) and {name} (T, {width}); got {gripper.shape} and {values.shape}")
    if not (np.isfinite(gripper).all() and np.isfinite(values).all()):
        raise ValueError(f"gripper and {name} must be finite")
    return gripper, values


def next_gripper_event_positions(gripper: np.ndarray, tcp_position: np.ndarray) -> np.ndarray:
    """Per frame t of an episode, the tool-centre-point position at the first frame k > t whose
    gripper command has another sign than frame k-1's, else at the last frame.

    gripper (T,) commands (sign: open / closed); tcp_position (T, 3) [m]. Returns float32 (T, 3)."""
    gripper, tcp_position = _checked(gripper, tcp_position, "tcp_position", 3)
    return tcp_position[next_gripper_event_frames(gripper)].astype(np.float32)
