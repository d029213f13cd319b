"""Checks of user-supplied inputs: each bad field raises a ValueError that names it and says what is accepted.

Observation dict of `TriVLA.predict_action_chunk`:
    "static_rgb", "wrist_rgb": uint8 numpy (H, W, 3), H = W = the config's image size (224);
    "instruction": non-empty str; "state": float numpy (state_dim,), finite;
    "embodiment_id": int in [0, num_embodiments) (optional, default 0).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

CAMERA_KEYS = ("static_rgb", "wrist_rgb")
REQUIRED_KEYS = CAMERA_KEYS + ("instruction", "state")


def check_image(name: str, image: Any, size: int) -> np.ndarray:
    """A uint8 (size, size, 3) RGB array, else ValueError naming `name`."""
    if image is None:
        raise ValueError(f"{name} is missing: give a uint8 ({size}, {size}, 3) RGB image")
    if not isinstance(image, np.ndarray):
        raise ValueError(
            f"{name} must be a numpy array of dtype uint8, shape ({size}, {size}, 3); got {type(image).__name__}"
        )
    if image.dtype != np.uint8:
        raise ValueError(f"{name} must have dtype uint8 (0-255 RGB); got {image.dtype}")
    if image.shape != (size, size, 3):
        raise ValueError(f"{name} must have shape ({size}, {size}, 3); got {image.shape}")
    return image


def check_state(name: str, state: Any, state_dim: int) -> np.ndarray:
    """A finite float (state_dim,) vector as float32, else ValueError naming `name`."""
    try:
        array = np.asarray(state)
    except Exception as exc:  # noqa: BLE001 - anything unconvertible is a bad input
        raise ValueError(f"{name} must be a float array of shape ({state_dim},): {exc}") from exc
    if array.dtype == object or not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f"{name} must be a float array of shape ({state_dim},); got dtype {array.dtype}")
    if array.shape != (state_dim,):
        raise ValueError(f"{name} must have shape ({state_dim},) (policy.state_dim); got {array.shape}")
    if not np.all(np.isfinite(array)):
        bad = np.flatnonzero(~np.isfinite(array)).tolist()
        raise ValueError(f"{name} has NaN or infinite entries at indices {bad}")
    return array.astype(np.float32)


def check_embodiment_id(name: str, embodiment_id: Any, num_embodiments: int) -> int:
    """An int in [0, num_embodiments), else ValueError naming `name`."""
    if isinstance(embodiment_id, (bool, np.bool_)) or not isinstance(embodiment_id, (int, np.integer)):
        raise ValueError(f"{name} must be an int in [0, {num_embodiments}); got {embodiment_id!r}")
    if not 0 <= int(embodiment_id) < num_embodiments:
        raise ValueError(
            f"{name} {int(embodiment_id)} is unknown: valid ids are 0..{num_embodiments - 1} (policy.num_embodiments)"
        )
    return int(embodiment_id)


def check_observation(observation: Any, *, image_size: int, state_dim: int, num_embodiments: int) -> dict[str, Any]:
    """Validated copy of an observation dict (instruction text is checked by the tokenizers later)."""
    if not isinstance(observation, Mapping):
        raise ValueError(
            f"observation must be a dict with keys {list(REQUIRED_KEYS)}; got {type(observation).__name__}"
        )
    missing = [k for k in REQUIRED_KEYS if k not in observation]
    if missing:
        raise ValueError(
            f"observation is missing {missing}; required keys: {list(REQUIRED_KEYS)} (+ optional 'embodiment_id')"
        )
    return {
        "static_rgb": check_image("observation['static_rgb']", observation["static_rgb"], image_size),
        "wrist_rgb": check_image("observation['wrist_rgb']", observation["wrist_rgb"], image_size),
        "instruction": observation["instruction"],
        "state": check_state("observation['state']", observation["state"], state_dim),
        "embodiment_id": check_embodiment_id(
            "observation['embodiment_id']", observation.get("embodiment_id", 0), num_embodiments
        ),
    }
