"""Where the Franka Panda description shipped by the `example-robot-data` package lives."""

from __future__ import annotations

import sys
import sysconfig
from pathlib import Path

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
# The tool-centre-point frame between the fingertips: what the end-effector pose refers to.
EE_FRAME = "panda_hand_tcp"


def _candidate_share_dirs() -> list[Path]:
    roots = {Path(sys.prefix), Path(sysconfig.get_paths()["purelib"]) / "cmeel.prefix"}
    for entry in sys.path:
        roots.add(Path(entry) / "cmeel.prefix")
    return [root / "share" / "example-robot-data" for root in roots] + [
        root / "cmeel.prefix" / "share" / "example-robot-data" for root in roots
    ]


def example_robot_data_dir() -> Path:
    """The `share/example-robot-data` folder installed by pip's example-robot-data package."""
    for candidate in _candidate_share_dirs():
        if (candidate / "robots" / "panda_description").is_dir():
            return candidate
    raise FileNotFoundError(
        "example-robot-data's Panda description was not found; install it with "
        "`pip install example-robot-data` (looked under: "
        + ", ".join(sorted({str(c) for c in _candidate_share_dirs()}))
        + ")"
    )


def panda_description_dir() -> Path:
    """The `robots/panda_description` folder (urdf/, meshes/visual/*.dae, meshes/collision/*.stl)."""
    return example_robot_data_dir() / "robots" / "panda_description"


def original_panda_urdf() -> Path:
    """The upstream URDF. pinocchio reads it as is; Drake needs `panda_assets.drake_panda_urdf()`."""
    return panda_description_dir() / "urdf" / "panda.urdf"
