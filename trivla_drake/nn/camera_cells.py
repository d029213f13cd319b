"""Where on the table each image token's cell looks: a fixed camera's pinhole geometry, in plain numbers.

A calibration is 12 numbers, the layout of `PolicyConfig.grounding_anchor_camera`:
    x, y, z [m], roll, pitch, yaw [rad]   the camera frame C in the world, or for a camera on the hand in
                                          the tool-centre point's frame (Drake's convention:
                                          R_WC = Rz(yaw) Ry(pitch) Rx(roll); C looks along +z, x right, y down)
    fx, fy, cx, cy [pixels]               focal lengths and principal point (pixel centres at integers)
    width, height [pixels]                the image the calibration is for
Images of another size are taken as scaled copies (System 2 resizes frames to its image size).
`station/cameras.py: camera_calibration` reads one from a scenario's camera.
"""

from __future__ import annotations

import math

import numpy as np

CALIBRATION_FIELDS = ("x", "y", "z", "roll", "pitch", "yaw", "fx", "fy", "cx", "cy", "width", "height")

# The plane the grounding's anchor places lie on: a resting block's centre (4.5 cm cubes), where the hand
# closes on it [m].
ANCHOR_PLANE_HEIGHT = 0.0225


def check_calibration(calibration, field: str) -> None:
    """ValueError naming `field` unless `calibration` is 12 finite numbers with positive focal lengths and
    image size, laid out as CALIBRATION_FIELDS."""
    try:
        values = list(calibration)
    except TypeError:
        raise ValueError(f"{field} must be {len(CALIBRATION_FIELDS)} numbers ({', '.join(CALIBRATION_FIELDS)}); "
                         f"got {calibration!r}") from None
    if len(values) != len(CALIBRATION_FIELDS):
        raise ValueError(f"{field} must have {len(CALIBRATION_FIELDS)} numbers ({', '.join(CALIBRATION_FIELDS)}); "
                         f"got {len(values)}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values):
        raise ValueError(f"{field} must be finite numbers; got {values}")
    for name in ("fx", "fy", "width", "height"):
        if values[CALIBRATION_FIELDS.index(name)] <= 0:
            raise ValueError(f"{field}: {name} must be positive; got {values[CALIBRATION_FIELDS.index(name)]}")


def check_looks_down(calibration, height: float, field: str) -> None:
    """ValueError naming `field` unless `calibration` (a camera fixed in the world) is valid and sees the
    plane z = `height` [m] through all of its image: the rays through the image's four corners come down
    to it (the rays that do form a half-plane of pixels, so every cell's does too)."""
    check_calibration(calibration, field)
    width, height_px = (float(v) for v in list(calibration)[10:])
    cols, rows = np.meshgrid([-0.5, width - 0.5], [-0.5, height_px - 0.5])
    _meet_plane(calibration, _pixel_rays(calibration, cols, rows), height, field)


def rotation_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (3, 3), Drake's RollPitchYaw."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def camera_pose(calibration) -> tuple[np.ndarray, np.ndarray]:
    """The calibration's camera frame: rotation (3, 3) and position (3,) [m] in the frame it is given in."""
    x, y, z, roll, pitch, yaw = (float(v) for v in list(calibration)[:6])
    return rotation_from_rpy(roll, pitch, yaw), np.array([x, y, z])


def _pixel_rays(calibration, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Directions (K, 3) in the camera frame (z = 1) through the pixels (cols, rows), flattened row-major."""
    fx, fy, cx, cy = (float(v) for v in list(calibration)[6:10])
    return np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones_like(rows)], axis=-1).reshape(-1, 3)


def _meet_plane(calibration, rays: np.ndarray, height: float, field: str) -> np.ndarray:
    """Where camera-frame `rays` (K, 3) of a camera fixed in the world meet the plane z = `height` [m]:
    (K, 3) [m]; ValueError naming `field` if one does not come down to it."""
    rotation, origin = camera_pose(calibration)
    rays_w = rays @ rotation.T
    if np.any(rays_w[:, 2] >= 0) or origin[2] <= height:
        raise ValueError(f"{field}: the camera at z = {origin[2]:.3f} m does not look down onto z = {height:.3f} m "
                         "through all of its image")
    t = (height - origin[2]) / rays_w[:, 2]
    return origin + t[:, None] * rays_w


def cell_rays(calibration, grid: int, field: str = "calibration") -> np.ndarray:
    """Directions (grid * grid, 3) in the camera frame (z = 1) through the centres of the image's
    grid x grid cells, in row-major order (the order of System 2's image tokens after pixel shuffle)."""
    check_calibration(calibration, field)
    if grid < 1:
        raise ValueError(f"grid must be >= 1; got {grid}")
    width, height = (float(v) for v in list(calibration)[10:])
    centres = (np.arange(grid) + 0.5) / grid  # cell centres as fractions of the image
    rows, cols = np.meshgrid(centres * height - 0.5, centres * width - 0.5, indexing="ij")
    return _pixel_rays(calibration, cols, rows)


def cell_table_points(calibration, grid: int, height: float, field: str = "calibration") -> np.ndarray:
    """Where the ray through the centre of each of the image's grid x grid cells meets the plane
    z = `height` [m] of a camera fixed in the world: (grid * grid, 3) [m], cells in row-major order.
    ValueError naming `field` if a cell's ray does not come down to the plane."""
    return _meet_plane(calibration, cell_rays(calibration, grid, field), height, field)
