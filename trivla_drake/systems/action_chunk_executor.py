"""`ActionChunkExecutor`: plays System 1's action chunks one action per control tick."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem

from trivla_drake.robot.panda_kinematics import PandaKinematics
from trivla_drake.systems.action_executor import (
    ACTION_DIM,
    CLOSED_WIDTH,
    DEFAULT_ACTION_SPACE,
    OPEN_WIDTH,
    ActionSpace,
    apply_action,
)
from trivla_drake.systems.robot_base import base_pose_matrix


@dataclass(frozen=True)
class ChunkHistory:
    """The chunks still being played, oldest first, each with the sim time of its observation."""

    stamps: tuple[float, ...] = ()
    chunks: tuple[np.ndarray, ...] = ()

    def add(self, stamp: float, chunk: np.ndarray, keep: int) -> "ChunkHistory":
        if self.stamps and stamp == self.stamps[-1]:
            return self
        stamps = (self.stamps + (stamp,))[-keep:]
        chunks = (self.chunks + (np.array(chunk, dtype=np.float64),))[-keep:]
        return ChunkHistory(stamps, chunks)


def covering_chunks(chunk_s: float, period_s: float) -> int:
    """How many chunks can cover one tick when a chunk lasting `chunk_s` is observed every `period_s`
    seconds: the newest and those observed less than a chunk's duration before it, ceil(chunk_s / period_s)."""
    return max(1, math.ceil(chunk_s / period_s - 1e-9))  # 1e-9: 10 dt / (2 dt) is 5.000000000000001


def select_action(history: ChunkHistory, t: float, dt: float, ensemble_decay: float | None) -> np.ndarray | None:
    """The action for sim time t, or None when no chunk covers t.

    Action k of a chunk observed at time s is meant for time s + k dt, so after a latency L the
    first round(L / dt) actions are skipped, not replayed late. Without ensembling the newest
    chunk that covers t is played; with `ensemble_decay` m, every covering chunk i (0 = oldest)
    is averaged with weight exp(-m i), as in ACT's temporal ensembling.
    """
    candidates = []
    for stamp, chunk in zip(history.stamps, history.chunks):
        k = int(round((t - stamp) / dt))
        if 0 <= k < len(chunk):
            candidates.append(chunk[k])
    if not candidates:
        return None
    if ensemble_decay is None:
        return candidates[-1]
    weights = np.exp(-ensemble_decay * np.arange(len(candidates)))
    return np.average(np.stack(candidates), axis=0, weights=weights)


class ActionChunkExecutor(LeafSystem):
    """Turns action chunks into the diff-IK's end-effector target and the gripper command.

    Inputs: `action_chunk` (abstract float numpy (H, 7), PolicySystem's output, None before the
    first one), `action_chunk_stamp` (1-vector, sim time [s] of the chunk's observation),
    `robot_state` (18-vector, Panda q (7 arm [rad], 2 fingers [m]) then v [rad/s, m/s]; read at
    initialisation for the starting pose).
    Outputs: `ee_target` (RigidTransform X_WT: pose of `panda_hand_tcp` in the world [m]),
    `gripper_target` (1-vector, finger distance [m]), `action` (7-vector, the action applied at the
    last tick).
    Every 1 / control_rate_hz seconds (36 Hz), at offset_s + n / control_rate_hz, it applies one
    action (see trivla_drake/action.py for the action space); with no chunk covering the time, it holds
    the commanded pose.

    The actions, the workspace box and the commanded pose in the state are in the robot's base frame
    B (`panda_link0`), so the same actions move the hand the same way relative to its base wherever the
    base stands; `X_WB` (the base's pose in the world, identity by default) maps the commanded pose
    X_BT to the world for `ee_target`: X_WT = X_WB X_BT.
    """

    def __init__(
        self,
        space: ActionSpace = DEFAULT_ACTION_SPACE,
        *,
        ensemble_decay: float | None = None,
        keep_chunks: int = 4,
        kinematics: PandaKinematics | None = None,
        offset_s: float = 0.0,
        X_WB: RigidTransform | None = None,
    ):
        super().__init__()
        if ensemble_decay is not None and not (math.isfinite(ensemble_decay) and ensemble_decay >= 0):
            raise ValueError(f"ensemble_decay must be a finite number >= 0 or None, got {ensemble_decay}")
        if isinstance(keep_chunks, bool) or not isinstance(keep_chunks, (int, np.integer)) or keep_chunks < 1:
            raise ValueError(f"keep_chunks must be an integer >= 1 (chunks kept for ensembling), got {keep_chunks!r}")
        if not 0.0 <= offset_s < space.dt:
            raise ValueError(f"offset_s must be in [0, dt = {space.dt:g}), got {offset_s}")
        self._space = space
        self._decay = ensemble_decay
        self._keep = keep_chunks if ensemble_decay is not None else 1
        self._kinematics = kinematics or PandaKinematics()
        # None at the identity: the commanded pose is output as it is, bit for bit (no matmul).
        self._X_WB = base_pose_matrix(X_WB, "X_WB")
        self._chunk = self.DeclareAbstractInputPort("action_chunk", AbstractValue.Make(None))
        self._stamp = self.DeclareVectorInputPort("action_chunk_stamp", 1)
        self._robot_state = self.DeclareVectorInputPort("robot_state", 18)
        # Discrete state: commanded tcp pose [p (3), R (9 row-major)], width (1), last action (7),
        # and the number of ticks that played a policy action (the rest held the pose).
        self._pose_index = self.DeclareDiscreteState(13 + ACTION_DIM + 1)
        self._history_index = self.DeclareAbstractState(AbstractValue.Make(ChunkHistory()))
        self.DeclareInitializationUnrestrictedUpdateEvent(self._initialise)
        self.DeclarePeriodicUnrestrictedUpdateEvent(space.dt, offset_s, self._tick)
        # The outputs read the discrete state alone: no direct feedthrough from any input.
        state_only = {self.xd_ticket()}
        self.DeclareAbstractOutputPort("ee_target", lambda: AbstractValue.Make(RigidTransform()), self._calc_target,
                                       prerequisites_of_calc=state_only)
        self.DeclareVectorOutputPort("gripper_target", 1, self._calc_width, prerequisites_of_calc=state_only)
        self.DeclareVectorOutputPort("action", ACTION_DIM, self._calc_action, prerequisites_of_calc=state_only)

    @property
    def action_space(self) -> ActionSpace:
        """The action space (control rate, bounds) this executor applies."""
        return self._space

    def _initialise(self, context, state):
        q = self._robot_state.Eval(context)
        X = self._kinematics.ee_pose(q[:7])
        width = float(np.clip(q[7] + q[8], CLOSED_WIDTH, OPEN_WIDTH))
        vector = np.concatenate([X[:3, 3], X[:3, :3].reshape(-1), [width], np.zeros(ACTION_DIM), [0.0]])
        state.get_mutable_discrete_state(self._pose_index).SetFromVector(vector)
        state.get_mutable_abstract_state(self._history_index).set_value(ChunkHistory())

    def _tick(self, context, state):
        t = context.get_time()
        history = context.get_abstract_state(self._history_index).get_value()
        chunk = self._chunk.Eval(context)
        if chunk is not None:
            history = history.add(float(self._stamp.Eval(context)[0]), chunk, self._keep)
        vector = context.get_discrete_state(self._pose_index).value()
        X = np.eye(4)
        X[:3, 3] = vector[:3]
        X[:3, :3] = vector[3:12].reshape(3, 3)
        width, played = vector[12], vector[-1]
        action = select_action(history, t, self._space.dt, self._decay)
        if action is None:
            action = np.zeros(ACTION_DIM)  # hold the pose and the gripper
            action[6] = 1.0 if width > 0.5 * OPEN_WIDTH else -1.0
        else:
            played += 1
        X, width = apply_action(X, action, self._space)
        vector = np.concatenate([X[:3, 3], X[:3, :3].reshape(-1), [width], action, [played]])
        state.get_mutable_discrete_state(self._pose_index).SetFromVector(vector)
        state.get_mutable_abstract_state(self._history_index).set_value(history)

    def _calc_target(self, context, output):
        vector = context.get_discrete_state(self._pose_index).value()
        X_BT = np.eye(4)
        X_BT[:3, 3] = vector[:3]
        X_BT[:3, :3] = vector[3:12].reshape(3, 3)
        output.set_value(RigidTransform(X_BT if self._X_WB is None else self._X_WB @ X_BT))

    def _calc_width(self, context, output: BasicVector):
        output.SetAtIndex(0, context.get_discrete_state(self._pose_index).value()[12])

    def _calc_action(self, context, output: BasicVector):
        output.SetFromVector(context.get_discrete_state(self._pose_index).value()[13 : 13 + ACTION_DIM])

    def played_actions(self, context) -> int:
        """How many ticks so far applied a policy action rather than holding (this system's context)."""
        return int(context.get_discrete_state(self._pose_index).value()[-1])
