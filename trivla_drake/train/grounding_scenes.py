"""Rendered scenes for the instruction grounding: many more layouts than the demonstrations hold.

The grounding (nn/instruction_grounding.py) learns where the block an instruction names lies from the
demonstrations' frames. On those frames the shipped model's sub-goal lies a median 1.1 cm from its
label; on unseen scenes 2.3 cm (research/subgoal_trust). It has seen too few layouts. A demonstration
costs seconds of simulation; a rendered scene costs about 30 ms, and for a task whose first gripper
event is a grasp its label needs no simulation at all: the oracle's plan, made from the scene, says
where the hand will close.

Each scene: an instance of one of GROUNDING_SCENE_TASKS (in turn, two scenes each), sampled as `collect` samples its
episodes (`sample_task_instance`, training templates); even-numbered scenes keep the arm at its start
(as a demonstration's first frame), odd ones put it at a random point of the oracle's path from the
start to the grasp (inverse kinematics, the fingers open, up to APPROACH_SPREAD off the path, never
below the grasp). The label is the plan's closing tool-centre point, CLOSE_TRACKING_LAG higher: the
recorded demonstrations close there (the tracked tcp lags its command). The state is the arm's joint
angles, the fingers open, no velocity (the default 18-D Panda state).

The set is written once to a folder (atomically: a temporary folder renamed into place):
    meta.json       settings and counts
    static.npy      uint8 (scenes, S, S, 3)       wrist.npy   uint8 (scenes, S, S, 3)
    scenes.parquet  task, instruction, state (18), subgoal_position (3) [m], subgoal_yaw (2), along_approach
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from trivla_drake.train.atomic_folder import atomic_folder, ensure_cached_folder

GROUNDING_SCENES_FORMAT = 1
GROUNDING_SCENE_TASKS = ("lift_block", "place_in_bowl", "stack_block", "rotate_block_left",
                         "rotate_block_right", "unstack_block")
# The recorded tcp at a demonstration's first close lies this far above the plan's closing pose [m]
# (0.46 cm in z, 0.00 cm in x-y, spread 0.02 cm, over 27 of the 360 clean demonstrations; research/grounding_scenes).
CLOSE_TRACKING_LAG = np.array([0.0, 0.0, 0.0046])
APPROACH_SPREAD = 0.01  # standard deviation [m] of the approach points' offset from the oracle's path, per axis
IK_TOLERANCE = 0.002  # [m]: a scene whose arm pose misses its approach point by more is drawn again
FINGER_OPEN = 0.04  # each finger's position with the gripper open [m]


def grounding_scene_settings(*, scenes: int, seed: int, image_size: int) -> dict[str, Any]:
    """What a set depends on (its folder's key)."""
    if scenes < 1:
        raise ValueError(f"scenes must be >= 1; got {scenes}")
    return {"format": GROUNDING_SCENES_FORMAT, "scenes": int(scenes), "seed": int(seed),
            "image_size": int(image_size), "tasks": list(GROUNDING_SCENE_TASKS)}


def grounding_scene_key(settings: dict[str, Any]) -> str:
    """Short hash of the settings."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def quarter_turn_yaw(pose: np.ndarray) -> np.ndarray:
    """(cos 4 psi, sin 4 psi) of a downward tcp pose's yaw psi (data/subgoals.py's yaw features)."""
    from trivla_drake.tasks.scene import hand_yaw

    psi = hand_yaw(pose)
    return np.array([math.cos(4 * psi), math.sin(4 * psi)], dtype=np.float32)


def point_on_path(poses: list[np.ndarray], fraction: float) -> np.ndarray:
    """The pose `fraction` (0..1) of the way along a piecewise path through 4x4 `poses`, by length:
    positions linear, orientations turned along each leg in proportion."""
    import pinocchio as pin

    if len(poses) < 2 or not 0.0 <= fraction <= 1.0:
        raise ValueError(f"need at least 2 poses and a fraction in [0, 1]; got {len(poses)} and {fraction}")
    lengths = np.array([np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(poses[:-1], poses[1:])])
    ends = np.cumsum(lengths)
    at = fraction * ends[-1]
    leg = int(min(np.searchsorted(ends, at), len(lengths) - 1))
    along = (at - (ends[leg] - lengths[leg])) / lengths[leg] if lengths[leg] > 0 else 1.0
    a, b = poses[leg], poses[leg + 1]
    out = np.eye(4)
    out[:3, 3] = a[:3, 3] + along * (b[:3, 3] - a[:3, 3])
    out[:3, :3] = a[:3, :3] @ pin.exp3(along * pin.log3(a[:3, :3].T @ b[:3, :3]))
    return out


def sample_grounding_scene(index: int, seed: int, layout, kinematics) -> dict[str, Any]:
    """Scene `index` of a set: {"spec" (SceneSpec, the arm placed), "task", "instruction", "state" (18,),
    "subgoal_position" (3,) [m], "subgoal_yaw" (2,), "along_approach"} (module doc)."""
    from trivla_drake.action import GRIPPER_CLOSE
    from trivla_drake.robot.panda_ik import solve_ik
    from trivla_drake.tasks.scene import scene_from_spec, with_arm
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    task = get_task(GROUNDING_SCENE_TASKS[(index // 2) % len(GROUNDING_SCENE_TASKS)])
    along = index % 2 == 1
    rng = np.random.default_rng([int(seed), int(index)])
    for _ in range(20):
        spec, instance = sample_task_instance(task, rng, layout)
        plan = task.plan(instance.params, scene_from_spec(spec, layout))
        close = next((i for i, wp in enumerate(plan) if wp.gripper == GRIPPER_CLOSE), None)
        if close is None:
            raise RuntimeError(f"task {task.name}'s plan never closes the gripper: it cannot label grounding scenes")
        arm_q = np.asarray(spec.arm_q, dtype=float)
        if along:
            path = [kinematics.ee_pose(arm_q)] + [wp.pose for wp in plan[: close + 1]]
            target = point_on_path(path, float(rng.uniform()))
            target[:3, 3] += rng.normal(0.0, APPROACH_SPREAD, 3)
            target[2, 3] = max(target[2, 3], plan[close].pose[2, 3])
            arm_q, missed, _ = solve_ik(kinematics, target, arm_q)
            if missed > IK_TOLERANCE:
                continue
            spec = with_arm(spec, arm_q)
        return {
            "spec": spec, "task": task.name, "instruction": instance.instruction, "along_approach": along,
            "state": np.concatenate([arm_q, [FINGER_OPEN, FINGER_OPEN], np.zeros(9)]).astype(np.float32),
            "subgoal_position": (plan[close].pose[:3, 3] + CLOSE_TRACKING_LAG).astype(np.float32),
            "subgoal_yaw": quarter_turn_yaw(plan[close].pose),
        }
    raise RuntimeError(f"grounding scene {index}: no reachable approach point in 20 draws")


def generate_grounding_scenes(folder: str | os.PathLike, settings: dict[str, Any], *, progress: bool = True) -> Path:
    """Renders the scenes and writes the set to `folder` (atomically). Returns the folder."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from tqdm import tqdm

    from trivla_drake.robot.panda_kinematics import PandaKinematics
    from trivla_drake.train.vqa import SceneRenderer

    with atomic_folder(folder) as tmp:
        n, size = int(settings["scenes"]), int(settings["image_size"])
        renderer, kinematics = SceneRenderer(size), PandaKinematics()
        layout = renderer.layout()
        static = np.lib.format.open_memmap(tmp / "static.npy", mode="w+", dtype=np.uint8, shape=(n, size, size, 3))
        wrist = np.lib.format.open_memmap(tmp / "wrist.npy", mode="w+", dtype=np.uint8, shape=(n, size, size, 3))
        keys = ["task", "instruction", "state", "subgoal_position", "subgoal_yaw", "along_approach"]
        columns: dict[str, list] = {k: [] for k in keys}
        for i in tqdm(range(n), desc="rendering grounding scenes", unit="scene", disable=not progress):
            scene = sample_grounding_scene(i, int(settings["seed"]), layout, kinematics)
            static[i], wrist[i], _ = renderer.render(scene["spec"])
            for key in columns:
                value = scene[key]
                columns[key].append(value.tolist() if isinstance(value, np.ndarray) else value)
        for array in (static, wrist):
            array.flush()
        del static, wrist
        pq.write_table(pa.table(columns), tmp / "scenes.parquet")
        (tmp / "meta.json").write_text(json.dumps(settings, indent=2))
    return Path(folder)


def ensure_grounding_scenes(folder: str | os.PathLike, settings: dict[str, Any], *, progress: bool = True) -> Path:
    """The set in `folder`, rendered if absent. ValueError if `folder` holds something else or a set
    made with other settings (it is never overwritten)."""
    return ensure_cached_folder(folder, settings, lambda: generate_grounding_scenes(folder, settings, progress=progress),
                                what="grounding scenes")


class GroundingScenes:
    """A rendered set (memory-mapped views) with its labels."""

    def __init__(self, folder: str | os.PathLike) -> None:
        import pyarrow.parquet as pq

        self.folder = Path(folder)
        if not (self.folder / "meta.json").is_file():
            raise ValueError(f"{self.folder} holds no grounding scenes (meta.json is missing)")
        self.meta = json.loads((self.folder / "meta.json").read_text())
        if self.meta.get("format") != GROUNDING_SCENES_FORMAT:
            raise ValueError(f"{self.folder} holds grounding scenes of format {self.meta.get('format')!r}; this "
                             f"version reads format {GROUNDING_SCENES_FORMAT}: render them again in another folder")
        table = pq.read_table(self.folder / "scenes.parquet").to_pydict()
        self.tasks, self.instructions = table["task"], table["instruction"]
        self.along_approach = np.asarray(table["along_approach"], dtype=bool)
        self.state = np.asarray(table["state"], dtype=np.float32)
        self.subgoal_position = np.asarray(table["subgoal_position"], dtype=np.float32)
        self.subgoal_yaw = np.asarray(table["subgoal_yaw"], dtype=np.float32)
        self.static = np.load(self.folder / "static.npy", mmap_mode="r")
        self.wrist = np.load(self.folder / "wrist.npy", mmap_mode="r")

    def __len__(self) -> int:
        return len(self.instructions)
