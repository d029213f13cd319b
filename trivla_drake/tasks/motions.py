"""Waypoint plans for the scripted oracle: the building blocks (grasp, retreat) the tasks compose."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from trivla_drake.action import GRIPPER_CLOSE, GRIPPER_OPEN
from trivla_drake.tasks.scene import BLOCK_HALF, SceneState, fold_quarter_turn, tcp_pose

# Height of the tcp when moving between places [m]: an open hand clears every block and fixture.
TRANSIT_Z = 0.15
FAST, SLOW, CAREFUL = 0.3, 0.12, 0.06  # tcp speeds [m/s]


@dataclass(frozen=True)
class Waypoint:
    """One leg of a plan: move the commanded tcp to `pose` with the gripper at `gripper`."""

    # Target tcp pose in the world (4x4).
    pose: np.ndarray
    # +1 open, -1 close (applied from the start of the leg).
    gripper: float
    # Speed of the commanded tcp along the leg [m/s].
    speed: float = FAST
    # Rotation speed of the commanded tcp [rad/s].
    angular_speed: float = 1.2
    # Time to hold still at the end of the leg, e.g. while the fingers close [s].
    settle_s: float = 0.0
    # Distance the measured tcp must come within of `pose` before the leg ends [m] ...
    tolerance: float = 0.008
    # ... unless this much time passed since the commanded pose got there (contact legs) [s].
    timeout_s: float = 1.5
    label: str = ""


def moved(previous: Waypoint, position=None, *, yaw: float | None = None, gripper: float | None = None,
          **kwargs) -> Waypoint:
    """A waypoint like `previous` with another position / yaw / gripper."""
    pose = previous.pose.copy()
    if yaw is not None:
        pose = tcp_pose(pose[:3, 3], yaw)
    if position is not None:
        pose[:3, 3] = position
    return Waypoint(pose=pose, gripper=previous.gripper if gripper is None else gripper, **kwargs)


# Hand yaws the wrist reaches comfortably [rad]: yaw is about q1 - (q7 - 0.785) pointing down, and
# q7 stops at +/-2.9 rad, so large negative yaws run into the joint limit first.
YAW_RANGE = (-1.6, 2.0)


def grasp_yaws(scene: SceneState, color: str, *, turn: float = 0.0) -> list[float]:
    """Hand yaws that close the fingers on two opposite faces of the block and stay in `YAW_RANGE`
    (also after turning by `turn`), the one closest to 0 first."""
    base = fold_quarter_turn(scene.block_yaw(color))
    yaws = [base, base + math.pi / 2, base - math.pi / 2]
    return [y for y in yaws if YAW_RANGE[0] <= min(y, y + turn) and max(y, y + turn) <= YAW_RANGE[1]]


def grasp_yaw(scene: SceneState, color: str, at=None, *, turn: float = 0.0) -> float:
    """The grasp yaw (see `grasp_yaws`) whose hand body keeps clearest of tall things at `at`
    (default: the block), also after turning by `turn`; among clear ones the closest to 0."""
    xy = scene.block_position(color)[:2] if at is None else np.asarray(at)[:2]
    base = scene.base_of(color)
    exclude = (color,) if base is None else (color, base)

    def clearance(yaw: float) -> float:
        return min(scene.hand_clearance(xy, yaw, exclude), scene.hand_clearance(xy, yaw + turn, exclude))

    # Clearances beyond 4 cm all count the same, so the wrist stays near its middle when it can.
    return max(grasp_yaws(scene, color, turn=turn), key=lambda yaw: (min(clearance(yaw), 0.04), -abs(yaw)))


def grasp_clearance(scene: SceneState, color: str, at=None, *, turn: float = 0.0) -> float:
    """The hand body's clearance [m] with the yaw `grasp_yaw` picks."""
    xy = scene.block_position(color)[:2] if at is None else np.asarray(at)[:2]
    yaw = grasp_yaw(scene, color, at, turn=turn)
    base = scene.base_of(color)
    exclude = (color,) if base is None else (color, base)
    return min(scene.hand_clearance(xy, yaw, exclude), scene.hand_clearance(xy, yaw + turn, exclude))


def retreat(scene: SceneState, gripper_closed: bool) -> list[Waypoint]:
    """Get the hand free before a new task: open it unless it carries a block, then rise."""
    plan: list[Waypoint] = []
    start = Waypoint(pose=scene.tcp.copy(), gripper=GRIPPER_CLOSE if gripper_closed else GRIPPER_OPEN)
    holding = scene.held_block() is not None
    if gripper_closed and not holding:
        start = moved(start, gripper=GRIPPER_OPEN, settle_s=0.3, timeout_s=0.5, label="release")
        plan.append(start)
    if scene.tcp[2, 3] < 0.1:
        up = scene.tcp[:3, 3] + np.array([0.0, 0.0, 0.12 - scene.tcp[2, 3]])
        plan.append(moved(start, up, speed=SLOW, label="rise"))
    return plan


def grasp(scene: SceneState, color: str, lift_to: float, *, yaw: float | None = None) -> list[Waypoint]:
    """Open hand above the block, down around it, close, lift the tcp to `lift_to` [m]."""
    p = scene.block_position(color)
    if yaw is None:
        yaw = grasp_yaw(scene, color)
    z = max(p[2] + 0.003, 0.022)
    above = Waypoint(tcp_pose([p[0], p[1], max(p[2] + 0.1, 0.12)], yaw), GRIPPER_OPEN, label="above block")
    down = moved(above, [p[0], p[1], z], speed=SLOW, tolerance=0.006, label="around block")
    close = moved(down, gripper=GRIPPER_CLOSE, settle_s=0.5, timeout_s=0.8, label="close")
    lift = moved(close, [p[0], p[1], lift_to], speed=SLOW, tolerance=0.015, label="lift")
    return [above, down, close, lift]


def place(position, yaw: float, *, release_z: float, approach_z: float = TRANSIT_Z) -> list[Waypoint]:
    """Carry a held block over `position`, lower the tcp to `release_z`, open, rise again."""
    x, y = float(position[0]), float(position[1])
    over = Waypoint(tcp_pose([x, y, approach_z], yaw), GRIPPER_CLOSE, tolerance=0.012, label="carry")
    down = moved(over, [x, y, release_z], speed=CAREFUL, tolerance=0.006, label="lower")
    release = moved(down, gripper=GRIPPER_OPEN, settle_s=0.4, timeout_s=0.6, label="release")
    up = moved(release, [x, y, approach_z], speed=SLOW, label="rise")
    return [over, down, release, up]


def press(position, *, top_z: float = 0.12, press_z: float = 0.035) -> list[Waypoint]:
    """Closed hand above `position`, push down to `press_z`, rise again."""
    x, y = float(position[0]), float(position[1])
    over = Waypoint(tcp_pose([x, y, top_z], 0.0), GRIPPER_CLOSE, label="above button")
    down = moved(over, [x, y, press_z], speed=SLOW, tolerance=0.004, timeout_s=0.6, label="press")
    up = moved(down, [x, y, top_z], speed=SLOW, label="release button")
    return [over, down, up]


def handle_grasp(scene: SceneState) -> list[Waypoint]:
    """Open hand above the drawer handle, down around the bar, close on it."""
    h = scene.handle_position()
    cabinet = scene.layout.cabinet
    yaw = math.atan2(cabinet[1, 0], cabinet[0, 0])  # fingers close across the bar, along the cabinet's y
    above = Waypoint(tcp_pose(h + [0.0, 0.0, 0.1], yaw), GRIPPER_OPEN, label="above handle")
    down = moved(above, h, speed=SLOW, tolerance=0.005, label="around handle")
    close = moved(down, gripper=GRIPPER_CLOSE, settle_s=0.5, timeout_s=0.8, label="close on handle")
    return [above, down, close]


def slide_drawer(scene: SceneState, plan: list[Waypoint], target_opening: float) -> list[Waypoint]:
    """Move the grasped handle until the drawer is at `target_opening`, let go, rise."""
    h = scene.handle_position()
    goal = h + (target_opening - scene.drawer_opening) * scene.layout.drawer_axis()
    pull = moved(plan[-1], goal, speed=SLOW, tolerance=0.01, timeout_s=0.8, label="slide drawer")
    release = moved(pull, gripper=GRIPPER_OPEN, settle_s=0.3, timeout_s=0.5, label="let go")
    up = moved(release, goal + [0.0, 0.0, 0.1], speed=SLOW, label="rise")
    return [pull, release, up]


def rotate_in_place(scene: SceneState, color: str, angle: float) -> list[Waypoint]:
    """Grasp the block, lift it 2 cm, turn it by `angle` [rad] about z, set it down, let go."""
    p = scene.block_position(color)
    yaw = grasp_yaw(scene, color, turn=angle)
    plan = grasp(scene, color, lift_to=p[2] + 0.02, yaw=yaw)
    turned = moved(plan[-1], yaw=yaw + angle, angular_speed=0.8, tolerance=0.01, label="turn")
    down = moved(turned, [p[0], p[1], p[2] + 0.004], speed=CAREFUL, tolerance=0.006, label="set down")
    release = moved(down, gripper=GRIPPER_OPEN, settle_s=0.4, timeout_s=0.6, label="release")
    up = moved(release, [p[0], p[1], 0.12], speed=SLOW, label="rise")
    return plan + [turned, down, release, up]


def push(scene: SceneState, color: str, direction: np.ndarray, *, start_gap: float = 0.065,
         travel: float = 0.11) -> list[Waypoint]:
    """Closed fingers lowered beside the block, moved `travel` [m] along `direction` through it."""
    p = scene.block_position(color)
    d = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    yaw = math.atan2(d[1], d[0])  # the fingers close across the push direction: a wide paddle
    start = p - start_gap * d
    over = Waypoint(tcp_pose([start[0], start[1], 0.1], yaw), GRIPPER_CLOSE, label="above start")
    down = moved(over, [start[0], start[1], BLOCK_HALF], speed=SLOW, tolerance=0.006, label="lower")
    end = start + travel * d
    shove = moved(down, [end[0], end[1], BLOCK_HALF], speed=0.08, tolerance=0.01, label="push")
    up = moved(shove, [end[0], end[1], 0.1], speed=SLOW, label="rise")
    return [over, down, shove, up]
