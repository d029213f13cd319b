"""The tabletop's state as plain numbers, and the geometric facts tasks are built from.

`SceneState` is a snapshot of everything a task predicate or the oracle needs (block poses,
drawer opening, lamp, tool-centre point). `SceneSpec` is what an episode starts from (block
placements, drawer opening, lamp, arm posture). `Layout` holds the welded fixtures. None of this
imports Drake: `trivla_drake.tasks.sim` reads and writes them from and to a station's Context.

Frames and units: world frame (x away from the robot, y to its left, z up, table top at z = 0),
metres and radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

BLOCK_COLORS = ("red", "green", "blue")
BLOCK_SIZE = 0.045  # edge of the cubes [m]
BLOCK_HALF = BLOCK_SIZE / 2
# A block resting on the table has its centre at BLOCK_HALF; below this it counts as on a surface [m].
ON_TABLE_MAX_Z = 0.032
# Handle bar centre and cap rest position in their bodies' frames [m] (see models/drawer.sdf, button.sdf).
HANDLE_IN_DRAWER = np.array([-0.135, 0.0, 0.075])
DRAWER_MAX_OPENING = 0.15
# Opening direction of the drawer in the cabinet frame (joint axis -x).
DRAWER_AXIS_IN_CABINET = np.array([-1.0, 0.0, 0.0])
BOWL_INNER_HALF = 0.07  # half the bowl's inner width [m]
BOWL_OUTER_HALF = 0.08
# Fingers closer than this [m] count as closed on something (a 4.5 cm block keeps them at 0.045).
GRIPPER_CLOSED_WIDTH = 0.06
# The arm posture every episode's start is randomised around (the scenario's default) [rad].
HOME_ARM_Q = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785])
START_Q_SPREAD = np.array([0.2, 0.15, 0.2, 0.15, 0.2, 0.15, 0.3])


@dataclass(frozen=True)
class Layout:
    """The welded fixtures: their poses in the world (4x4) as read from the plant."""

    bowl: np.ndarray
    cabinet: np.ndarray
    button_housing: np.ndarray
    # Position of the button cap's body origin (top of the housing) when not pressed [m].
    cap_rest: np.ndarray

    @classmethod
    def default(cls) -> "Layout":
        """The layout of models/default.scenarios.yaml (for tests that run without a plant)."""
        housing = _pose(0.68, 0.12, 0.0, math.pi / 2)
        return cls(
            bowl=_pose(0.45, 0.3, 0.0),
            cabinet=_pose(0.72, -0.3, 0.0),
            button_housing=housing,
            cap_rest=(housing @ np.array([-0.035, 0.0, 0.04, 1.0]))[:3],
        )

    def drawer_axis(self) -> np.ndarray:
        """Unit vector along which the drawer opens, in the world."""
        return self.cabinet[:3, :3] @ DRAWER_AXIS_IN_CABINET

    def handle_position(self, opening: float) -> np.ndarray:
        """World position of the handle bar's centre for a drawer opening [m]."""
        return (self.cabinet @ np.append(HANDLE_IN_DRAWER, 1.0))[:3] + opening * self.drawer_axis()


@dataclass
class SceneState:
    """A snapshot of the tabletop, from the plant's state (or built from a `SceneSpec`)."""

    layout: Layout
    # Colour -> 4x4 pose of the block's centre in the world.
    blocks: dict[str, np.ndarray]
    # Drawer joint position [m], 0 closed, 0.15 fully open.
    drawer_opening: float
    # Whether the button's lamp is lit.
    lamp_on: bool
    # Button cap joint position [m], 0 up, -0.015 fully pressed.
    button_press: float
    # Measured pose of `panda_hand_tcp` (4x4).
    tcp: np.ndarray
    # Distance between the fingers [m].
    finger_width: float
    # The arm's joint positions [rad].
    arm_q: np.ndarray = field(default_factory=lambda: HOME_ARM_Q.copy())

    # ---------------------------------------------------------------- geometry
    def block_position(self, color: str) -> np.ndarray:
        return self.blocks[color][:3, 3]

    def handle_position(self) -> np.ndarray:
        return self.layout.handle_position(self.drawer_opening)

    def cap_position(self) -> np.ndarray:
        return self.layout.cap_rest + np.array([0.0, 0.0, self.button_press])

    def is_upright(self, color: str) -> bool:
        """One of the block's faces points up (within about 18 degrees)."""
        return float(np.max(np.abs(self.blocks[color][2, :3]))) > 0.95

    def block_yaw(self, color: str) -> float:
        """Yaw of the block's faces about world z, folded into [-pi/4, pi/4) (a cube's symmetry)."""
        R = self.blocks[color][:3, :3]
        horizontal = int(np.argmin(np.abs(R[2, :])))  # the axis closest to horizontal
        axis = R[:, horizontal]
        return fold_quarter_turn(math.atan2(axis[1], axis[0]))

    def in_bowl(self, color: str) -> bool:
        """The block's centre is over the bowl's inside and low (resting in it, not carried over it)."""
        offset = self.layout.bowl[:3, :3].T @ (self.block_position(color) - self.layout.bowl[:3, 3])
        return bool(np.all(np.abs(offset[:2]) < BOWL_INNER_HALF - 0.01) and offset[2] < 0.06)

    def on_table(self, color: str) -> bool:
        """Resting on the table top (low, and not in the bowl)."""
        return bool(self.block_position(color)[2] < ON_TABLE_MAX_Z) and not self.in_bowl(color)

    def stacked_on(self, top: str, base: str) -> bool:
        """`top` rests on `base`: centred within 3 cm and one block height above it."""
        d = self.block_position(top) - self.block_position(base)
        return bool(np.hypot(d[0], d[1]) < 0.03 and 0.035 < d[2] < 0.056)

    def base_of(self, color: str) -> str | None:
        """The block `color` is stacked on, if any."""
        return next((c for c in self.blocks if c != color and self.stacked_on(color, c)), None)

    def has_block_on_top(self, color: str) -> bool:
        return any(self.stacked_on(c, color) for c in self.blocks if c != color)

    def gripper_closed(self) -> bool:
        return self.finger_width < GRIPPER_CLOSED_WIDTH

    def is_held(self, color: str) -> bool:
        """The block sits between closed fingers (its centre within 3 cm of the tcp)."""
        return self.gripper_closed() and float(np.linalg.norm(self.block_position(color) - self.tcp[:3, 3])) < 0.03

    def held_block(self) -> str | None:
        return next((c for c in self.blocks if self.is_held(c)), None)

    def hand_empty(self) -> bool:
        return self.held_block() is None

    # ---------------------------------------------------------------- free space
    def obstacle_clearance(self, xy: np.ndarray) -> float:
        """Distance [m] from a point on the table to the nearest fixture footprint (bowl, cabinet
        with its drawer and handle, button housing); negative inside one."""
        xy = np.asarray(xy, dtype=float)[:2]
        opening = self.drawer_opening
        boxes = [
            (self.layout.bowl, (-BOWL_OUTER_HALF, BOWL_OUTER_HALF), (-BOWL_OUTER_HALF, BOWL_OUTER_HALF)),
            # Cabinet body plus the drawer and its handle sticking out along -x.
            (self.layout.cabinet, (-0.145 - opening, 0.1), (-0.12, 0.12)),
            (self.layout.button_housing, (-0.07, 0.07), (-0.04, 0.04)),
        ]
        return min(_box_distance(xy, pose, xs, ys) for pose, xs, ys in boxes)

    def hand_clearance(self, xy: np.ndarray, yaw: float, exclude: tuple[str, ...] = ()) -> float:
        """Distance [m] from the footprint of a low, downward hand at `xy` with `yaw` to what is tall
        enough to hit the hand's body (not just its fingers): the cabinet with its drawer and handle,
        and stacked blocks other than `exclude`. Negative when they overlap."""
        c, s = math.cos(yaw), math.sin(yaw)
        along = np.array([s, -c])  # the fingers' closing direction: the hand is long this way
        across = np.array([c, s])
        centre = np.asarray(xy, dtype=float)[:2]
        points = [
            centre + a * along + b * across
            for a in np.linspace(-HAND_HALF_LENGTH, HAND_HALF_LENGTH, 11)
            for b in (-HAND_HALF_WIDTH, 0.0, HAND_HALF_WIDTH)
        ]
        opening = self.drawer_opening
        clearance = min(
            _box_distance(p, self.layout.cabinet, (-0.145 - opening, 0.1), (-0.12, 0.12)) for p in points
        )
        for color in self.blocks:
            if color in exclude or self.block_position(color)[2] < 0.05:
                continue
            top = self.block_position(color)[:2]
            reach = min(np.linalg.norm(p - top) for p in points) - BLOCK_HALF * math.sqrt(2)
            clearance = min(clearance, reach)
        return float(clearance)

    def block_clearance(self, xy: np.ndarray, exclude: tuple[str, ...] = ()) -> float:
        """Distance [m] from a point to the nearest block centre not in `exclude` (inf if none)."""
        xy = np.asarray(xy, dtype=float)[:2]
        distances = [np.linalg.norm(self.block_position(c)[:2] - xy) for c in self.blocks if c not in exclude]
        return float(min(distances, default=math.inf))

    def in_work_area(self, xy: np.ndarray) -> bool:
        """Inside the area blocks are placed in and pushed to."""
        x, y = np.asarray(xy, dtype=float)[:2]
        return bool(WORK_AREA_LOW[0] <= x <= WORK_AREA_HIGH[0] and WORK_AREA_LOW[1] <= y <= WORK_AREA_HIGH[1])


# Footprint of the Panda hand's body around the tcp [m]: long along the fingers' closing direction.
HAND_HALF_LENGTH = 0.11
HAND_HALF_WIDTH = 0.04
# Where blocks are placed at random, and may be pushed to (block centres) [m].
WORK_AREA_LOW = np.array([0.32, -0.16])
WORK_AREA_HIGH = np.array([0.60, 0.19])
# Sampled blocks start at least this far apart (centre to centre) [m]: an open hand fits between.
MIN_BLOCK_SEPARATION = 0.09


@dataclass(frozen=True)
class BlockPlacement:
    """Where a block starts: centre position [m] and yaw about world z [rad]."""

    position: tuple[float, float, float]
    yaw: float


@dataclass(frozen=True)
class SceneSpec:
    """An episode's initial state."""

    blocks: dict[str, BlockPlacement]
    drawer_opening: float = 0.0
    lamp_on: bool = False
    arm_q: tuple[float, ...] = tuple(HOME_ARM_Q)

    def to_dict(self) -> dict:
        """JSON-able form (recorded with episodes)."""
        return {
            "blocks": {c: {"position": list(b.position), "yaw": b.yaw} for c, b in self.blocks.items()},
            "drawer_opening": self.drawer_opening,
            "lamp_on": self.lamp_on,
            "arm_q": list(self.arm_q),
        }


def scene_from_spec(spec: SceneSpec, layout: Layout, tcp: np.ndarray | None = None) -> SceneState:
    """The `SceneState` an episode starts in (the hand open, at `tcp` or far above the table)."""
    if tcp is None:
        tcp = _pose(0.45, 0.0, 0.4, 0.0)
    blocks = {c: _pose(*b.position, b.yaw) for c, b in spec.blocks.items()}
    return SceneState(
        layout=layout,
        blocks=blocks,
        drawer_opening=spec.drawer_opening,
        lamp_on=spec.lamp_on,
        button_press=0.0,
        tcp=tcp,
        finger_width=0.08,
        arm_q=np.asarray(spec.arm_q, dtype=float),
    )


def sample_scene(
    rng: np.random.Generator,
    layout: Layout,
    *,
    stack: bool = False,
    drawer_open: bool | None = None,
    lamp_on: bool | None = None,
) -> SceneSpec:
    """A random initial state: blocks apart in the work area (with `stack`, one on another), the
    drawer closed or open, the lamp off or on (random when None), the arm near its home posture."""
    if drawer_open is None:
        drawer_open = bool(rng.random() < 0.5)
    if lamp_on is None:
        lamp_on = bool(rng.random() < 0.5)
    opening = float(rng.uniform(0.11, 0.14)) if drawer_open else 0.0
    probe = scene_from_spec(SceneSpec(blocks={}, drawer_opening=opening), layout)
    colors = list(BLOCK_COLORS)
    rng.shuffle(colors)
    on_table = colors[:-1] if stack else colors
    for _ in range(1000):
        positions: list[np.ndarray] = []
        for _color in on_table:
            for _ in range(200):
                xy = rng.uniform(WORK_AREA_LOW + 0.02, WORK_AREA_HIGH - 0.02)
                if probe.obstacle_clearance(xy) < 0.05:
                    continue
                if all(np.linalg.norm(xy - p) >= MIN_BLOCK_SEPARATION for p in positions):
                    positions.append(xy)
                    break
        if len(positions) == len(on_table):
            break
    else:  # pragma: no cover - the work area is far larger than three blocks need
        raise RuntimeError("could not place the blocks apart; the work area is too small")
    blocks = {
        c: BlockPlacement((float(xy[0]), float(xy[1]), BLOCK_HALF), float(rng.uniform(-math.pi / 4, math.pi / 4)))
        for c, xy in zip(on_table, positions)
    }
    if stack:
        base = on_table[int(rng.integers(len(on_table)))]
        bx, by, _ = blocks[base].position
        blocks[colors[-1]] = BlockPlacement(
            (bx, by, BLOCK_HALF + BLOCK_SIZE + 0.0005), blocks[base].yaw + float(rng.uniform(-0.15, 0.15))
        )
    arm_q = HOME_ARM_Q + rng.uniform(-1.0, 1.0, 7) * START_Q_SPREAD
    return SceneSpec(
        blocks={c: blocks[c] for c in BLOCK_COLORS},
        drawer_opening=opening,
        lamp_on=lamp_on,
        arm_q=tuple(float(q) for q in arm_q),
    )


def with_arm(spec: SceneSpec, arm_q) -> SceneSpec:
    """`spec` with another arm posture."""
    return replace(spec, arm_q=tuple(float(q) for q in arm_q))


# ---------------------------------------------------------------- small geometry helpers
def fold_quarter_turn(angle: float) -> float:
    """An angle folded into [-pi/4, pi/4) (modulo a quarter turn)."""
    return (angle + math.pi / 4) % (math.pi / 2) - math.pi / 4


def yaw_to_faces_deg(yaw: float, block_yaw: float) -> float:
    """A hand's yaw against a block's faces at `block_yaw` (both [rad]), in degrees modulo a quarter
    turn: in [-45, 45); near +-45 the open fingers come down on the block's corners."""
    return math.degrees(fold_quarter_turn(float(yaw) - float(block_yaw)))


def yaw_rotation(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def hand_down(yaw: float) -> np.ndarray:
    """Orientation of the tcp pointing down, its fingers closing along (sin yaw, -cos yaw, 0)."""
    return yaw_rotation(yaw) @ np.diag([1.0, -1.0, -1.0])


def tcp_pose(position, yaw: float) -> np.ndarray:
    """4x4 pose of the tcp pointing down at `position` with `yaw`."""
    X = np.eye(4)
    X[:3, :3] = hand_down(yaw)
    X[:3, 3] = position
    return X


def hand_yaw(X_tcp: np.ndarray) -> float:
    """The yaw of a (roughly) downward tcp, the inverse of `hand_down`."""
    x_axis = X_tcp[:3, 0]
    return math.atan2(x_axis[1], x_axis[0])


def _pose(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = yaw_rotation(yaw)
    X[:3, 3] = (x, y, z)
    return X


def _box_distance(xy: np.ndarray, pose: np.ndarray, xs: tuple[float, float], ys: tuple[float, float]) -> float:
    """Signed distance in the plane from `xy` to a rectangle given in `pose`'s frame."""
    local = pose[:2, :2].T @ (xy - pose[:2, 3])
    dx = max(xs[0] - local[0], local[0] - xs[1])
    dy = max(ys[0] - local[1], local[1] - ys[1])
    if dx <= 0 and dy <= 0:
        return max(dx, dy)
    return math.hypot(max(dx, 0.0), max(dy, 0.0))
