"""The episode runner: one task (or a chain of five) from a seeded initial state, a policy acting at
the control rate, success checked after every step from the simulator's state.

Every random choice of an episode (scene, target block, instruction, start posture, and the seed
given to the policy) comes from the episode's seed, and `TabletopEnv.reset` returns the simulation
(reused within a process) to a clean state, so an episode's outcome does not depend on which
process runs it or what ran before.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trivla_drake.eval.action_noise import Disturbance, DisturbanceState
from trivla_drake.eval.env import SimulationError, TabletopEnv
from trivla_drake.eval.policies import Policy, as_action_rows
from trivla_drake.station.scenario import Scenario
from trivla_drake.systems.action_executor import ACTION_HIGH, ACTION_LOW
from trivla_drake.tasks.chain_benchmark import benchmark_scene, subtask_instance
from trivla_drake.tasks.chains import CHAIN_LENGTH, next_chain_task, sample_chain_scene
from trivla_drake.tasks.suite import TaskInstance, get_task, sample_task_instance

if TYPE_CHECKING:
    from trivla_drake.eval.episode_starts import EpisodeStart
    from trivla_drake.tasks.chain_benchmark import BenchmarkChain

_log = logging.getLogger(__name__)


_ENVS: dict[int | None, TabletopEnv] = {}


def shared_env(image_size: int | None, scenario: Scenario | None = None) -> TabletopEnv:
    """A TabletopEnv for this process, reused across episodes (for the default scenario)."""
    if scenario is not None:
        return TabletopEnv(scenario, image_size=image_size)
    if image_size not in _ENVS:
        _ENVS[image_size] = TabletopEnv(image_size=image_size)
    return _ENVS[image_size]


def derive_seed(seed: int, *keys: int | str) -> int:
    """A 32-bit seed from a base seed and keys (names hashed with crc32, stable across processes).

    numpy's SeedSequence drops trailing zero words, so `(seed, k)` and `(seed, k, 0)` give one seed: every purpose
    passes a fixed number of keys (a task and an index; "chain" and an index; ...), never a prefix of another's.
    Mixing in the key count would avoid that but change every stored scene and evaluation, so it stays."""
    words = [int(seed) & 0xFFFFFFFF] + [zlib.crc32(k.encode()) if isinstance(k, str) else int(k) for k in keys]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


@dataclass
class Trajectory:
    """What a demonstration records, one row per control step (the terminal state is not a row)."""

    states: list[np.ndarray] = field(default_factory=list)  # (18,) panda.state
    actions: list[np.ndarray] = field(default_factory=list)  # (7,) the action applied (clipped)
    tcp_poses: list[np.ndarray] = field(default_factory=list)  # (7,) xyz + quaternion wxyz, measured
    images: dict[str, list[np.ndarray]] = field(default_factory=dict)  # key -> (H, W, 3) uint8
    # Whether the applied action was disturbed (collection with action noise; the recorded action is
    # the policy's own either way).
    perturbed: list[bool] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.actions)


@dataclass
class EpisodeResult:
    """The outcome of one episode."""

    task: str
    instruction: str
    params: tuple[str, ...]
    seed: int
    success: bool
    steps: int
    reason: str = ""  # why it failed ("" on success)
    trajectory: Trajectory | None = None
    # The tasks completed first, unrecorded, by the episode's start (`run_episode(start=...)`, a chain prelude), in
    # order.
    prelude: tuple[str, ...] = ()
    # Whether the episode's start failed or left the task no way to start (then `reason` says why and no step ran).
    start_failed: bool = False
    # With a hold check (`run_episode(hold_check=...)`): whether the success still held after the hand was held
    # still that long; None without a hold check or without a success.
    lasted: bool | None = None

    def to_dict(self) -> dict:
        out = {
            "task": self.task,
            "instruction": self.instruction,
            "params": list(self.params),
            "seed": self.seed,
            "success": self.success,
            "steps": self.steps,
            "reason": self.reason,
        }
        if self.prelude:
            out["prelude"] = list(self.prelude)
        if self.lasted is not None:
            out["lasted"] = self.lasted
        return out


@dataclass
class ChainResult:
    """The outcome of a chain: how many tasks in a row succeeded, and each task's result."""

    seed: int
    completed: int
    subtasks: list[EpisodeResult]
    reason: str = ""
    # With a hold check: how many tasks in a row succeeded and still held after the hold (None without).
    completed_lasting: int | None = None
    # A stored benchmark chain's index (None for a chain drawn as it goes), and for each subtask attempted whether its
    # stored parameters were among the task's candidates in the state the policy had left (CALVIN attempts it anyway).
    chain_index: int | None = None
    stored_task_feasible: list[bool] | None = None

    def to_dict(self) -> dict:
        out = {
            "seed": self.seed,
            "completed": self.completed,
            "reason": self.reason,
            "subtasks": [s.to_dict() for s in self.subtasks],
        }
        if self.completed_lasting is not None:
            out["completed_lasting"] = self.completed_lasting
        if self.chain_index is not None:
            out["chain_index"] = self.chain_index
            out["stored_task_feasible"] = list(self.stored_task_feasible or [])
        return out


# The longest hold check `evaluate --set hold_check=S` takes [s].
MAX_HOLD_CHECK_S = 10.0


def check_hold_check(seconds: float | None, name: str = "hold_check") -> None:
    """A hold check is None (off) or a finite time in (0, MAX_HOLD_CHECK_S] seconds."""
    if seconds is None:
        return
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 < seconds <= MAX_HOLD_CHECK_S:
        raise ValueError(f"{name} must be a time in seconds above 0 and at most {MAX_HOLD_CHECK_S:g} (how long the "
                         f"hand holds still before a success is asked again), got {seconds!r}")


def hold_steps(env: TabletopEnv, seconds: float | None) -> int:
    """The control steps of a hold check of `seconds`, checked by the caller (0 without one; at least 1 with one)."""
    return 0 if seconds is None else max(1, round(seconds * env.action_space.control_rate_hz))


def hold_still(env: TabletopEnv, steps: int, *, obs: dict | None = None, recorder: _Recorder | None = None) -> dict | None:
    """`steps` control steps of zero hand motion, the gripper keeping its last command (a lifted block stays in the
    hand, a released one stays released); returns the last observation (`obs` after no step). The recorder, if any,
    gets the frames of the hold, starting with `obs`, the observation before it (no trajectory rows: nothing the
    policy did)."""
    hold = np.zeros(7)
    hold[6] = env.last_action[6]
    if recorder is not None and obs is None:
        raise ValueError("hold_still: a recorder needs obs, the observation before the hold")
    images = recorder is not None and recorder.needs_images(env)
    for _ in range(steps):
        if recorder is not None:
            recorder.add(obs, None)
        obs = env.step(hold, images=images)
    return obs


class _Recorder:
    """Collects the rows of a trajectory and/or video frames."""

    def __init__(self, keep_trajectory: bool, video_path: str | Path | None, fps: float):
        self.trajectory = Trajectory() if keep_trajectory else None
        self.frames: list[np.ndarray] | None = [] if video_path is not None else None
        self.video_path = video_path
        self.fps = fps

    def needs_images(self, env: TabletopEnv) -> bool:
        """Whether every step's camera images are recorded (video or a trajectory with images)."""
        return env.has_cameras and (self.frames is not None or self.trajectory is not None)

    def add(self, obs: dict, action: np.ndarray | None, perturbed: bool = False) -> None:
        if self.frames is not None and "static_rgb" in obs:
            self.frames.append(np.concatenate([obs["static_rgb"], obs["wrist_rgb"]], axis=1))
        if self.trajectory is not None and action is not None:
            t = self.trajectory
            t.states.append(np.asarray(obs["state"], dtype=np.float32))
            t.actions.append(np.clip(action, ACTION_LOW, ACTION_HIGH).astype(np.float32))
            t.tcp_poses.append(_pose7(obs["tcp_pose"]))
            t.perturbed.append(bool(perturbed))
            for key in ("static_rgb", "wrist_rgb"):
                if key in obs:
                    t.images.setdefault(key, []).append(obs[key])

    def finish(self) -> None:
        if self.frames:
            from trivla_drake.data.video import write_video

            write_video(self.video_path, np.stack(self.frames), self.fps)


def _pose7(X: np.ndarray) -> np.ndarray:
    from pydrake.math import RotationMatrix

    q = RotationMatrix(X[:3, :3]).ToQuaternion()
    return np.array([*X[:3, 3], q.w(), q.x(), q.y(), q.z()], dtype=np.float32)


def _run_subtask(
    env: TabletopEnv,
    obs: dict,
    policy: Policy,
    instance: TaskInstance,
    seed: int,
    max_steps: int,
    recorder: _Recorder,
    disturbance: DisturbanceState | None = None,
    hold: int = 0,
) -> tuple[EpisodeResult, dict]:
    """Drive `policy` on one task from the env's current state until success or `max_steps`;
    `disturbance` perturbs the applied actions (the recorded ones stay the policy's). With `hold` > 0 steps, a
    success is followed by that many steps of the hand held still (`hold_still`) and the predicate is asked again
    (`EpisodeResult.lasted`); the episode's `steps` are the policy's only."""
    task = get_task(instance.task)
    initial = env.scene()
    result = EpisodeResult(instance.task, instance.instruction, instance.params, seed, False, 0)
    if task.success(instance.params, initial, initial):
        result.reason = "predicate already true at the start (not counted as a success)"
        return result, obs
    policy.reset(instance.instruction, seed)
    queue: list[np.ndarray] = []
    every_frame = recorder.needs_images(env)
    step = 0
    while step < max_steps:
        obs["instruction"] = instance.instruction
        if not queue:
            if policy.privileged:
                obs["privileged"] = {"scene": env.scene(), "task": instance}
            if policy.uses_images and env.has_cameras and "static_rgb" not in obs:
                obs.update(env.images())  # rendered only when the policy looks
            queue = list(as_action_rows(policy.act(obs)))
        action = queue.pop(0)
        applied, perturbed = (action, False) if disturbance is None else disturbance.apply(action, obs)
        recorder.add(obs, action, perturbed)
        obs = env.step(applied, images=every_frame)
        step += 1
        if task.success(instance.params, initial, env.scene()):
            result.success, result.steps = True, step
            if hold > 0:
                try:
                    obs = hold_still(env, hold, obs=obs, recorder=recorder)
                    result.lasted = bool(task.success(instance.params, initial, env.scene()))
                except SimulationError as error:  # the success stands; it did not last, and nothing can follow
                    result.lasted = False
                    result.reason = f"hold check: {error}"
            return result, obs
    result.steps = step
    result.reason = f"timeout: no success within {max_steps} steps"
    return result, obs


def run_unrecorded(
    env: TabletopEnv, obs: dict, policy: Policy, instance: TaskInstance, seed: int
) -> tuple[EpisodeResult, dict]:
    """`policy` drives one task from the env's current state within the task's own step budget, nothing recorded
    and nothing disturbed (the tasks of an episode start, eval/episode_starts.py); returns (its result, the last
    observation)."""
    unrecorded = _Recorder(False, None, env.action_space.control_rate_hz)
    return _run_subtask(env, obs, policy, instance, seed, get_task(instance.task).max_steps, unrecorded)


def run_episode(
    task_name: str,
    seed: int,
    policy: Policy,
    *,
    paraphrase: bool = False,
    image_size: int | None = None,
    video_path: str | Path | None = None,
    keep_trajectory: bool = False,
    max_steps: int | None = None,
    scenario: Scenario | None = None,
    perturbation: Disturbance | None = None,
    start: EpisodeStart | None = None,
    hold_check: float | None = None,
) -> EpisodeResult:
    """One episode of `task_name` from the initial state drawn with `seed`.

    `hold_check` (seconds): at a success the hand is then held still that long, the gripper keeping its last
    command, and the task's predicate asked again (`EpisodeResult.lasted`): a stacked block let go tilted, which the
    predicate counts at the instant it holds, may have fallen off by then (research/predicate_audit/).

    `perturbation` (a registered perturbation, eval/perturbations.py, e.g. DART's bursts) disturbs the applied
    actions; its random draws come from their own stream derived from `seed`, so the scene is the same with and
    without.

    `start` (a registered episode start, eval/episode_starts.py, e.g. a chain prelude: the oracle first completes
    other tasks of a chain, unrecorded and undisturbed) acts after the reset; the episode's task then starts where
    it left the scene and the hand, its parameters and instruction drawn in that state. A start that fails, or
    leaves the task no way to start, fails the episode with the reason (`EpisodeResult.start_failed`).

    A simulation failure (or a policy raising) ends the episode as a failure with its reason; it
    never escapes. `image_size` None renders no images unless the policy uses them or a video is
    recorded (then 224).
    """
    task = get_task(task_name)
    if start is not None and not callable(getattr(start, "begin", None)):
        raise TypeError(f"start must be an episode start (eval/episode_starts.py, make_episode_start), got {start!r}")
    check_hold_check(hold_check)
    if image_size is None and (policy.uses_images or video_path is not None):
        image_size = 224
    env = shared_env(image_size, scenario)
    rng = np.random.default_rng(seed)
    spec, instance = sample_task_instance(task, rng, env.layout(), paraphrase=paraphrase)
    recorder = _Recorder(keep_trajectory, video_path, env.action_space.control_rate_hz)
    policy_seed = int(rng.integers(2**31))
    done: tuple[str, ...] = ()
    why = ""  # why the start left no episode to run
    try:
        obs = env.reset(spec)
        if start is not None:
            started = start.begin(env, obs, task_name, seed, paraphrase)
            obs, done, why = started.obs, started.prelude, started.reason
            instance = started.instance or instance
            if recorder.needs_images(env):  # the unrecorded start's last step rendered none
                obs.update(env.images())
        if why:
            result = EpisodeResult(instance.task, instance.instruction, instance.params, seed, False, 0, why,
                                   start_failed=True)
        else:
            disturbance = None
            if perturbation is not None:
                disturbance = perturbation.start(np.random.default_rng(derive_seed(seed, "action_noise")))
            result, obs = _run_subtask(
                env, obs, policy, instance, policy_seed, max_steps or task.max_steps, recorder, disturbance,
                hold_steps(env, hold_check)
            )
            recorder.add(obs, None)
    except Exception as error:  # noqa: BLE001 - any failure is this episode's failure, the run goes on
        _log.warning("episode %s seed %d failed: %s", task_name, seed, error)
        result = EpisodeResult(instance.task, instance.instruction, instance.params, seed, False, env.step_index)
        result.reason = f"{type(error).__name__}: {error}"
    result.seed = seed
    result.prelude = done
    result.trajectory = recorder.trajectory
    try:
        recorder.finish()
    except Exception as error:  # noqa: BLE001 - a video that cannot be written does not fail the episode
        _log.warning("could not write video %s: %s", video_path, error)
    return result


def run_chain(
    seed: int,
    policy: Policy,
    *,
    length: int = CHAIN_LENGTH,
    paraphrase: bool = False,
    image_size: int | None = None,
    video_path: str | Path | None = None,
    scenario: Scenario | None = None,
    max_steps: int | None = None,
    hold_check: float | None = None,
    chain: BenchmarkChain | None = None,
) -> ChainResult:
    """A chain of `length` tasks from one initial state, stopping at the first failure; each task gets
    `max_steps` control steps (None: its own budget), as single episodes do.

    Without `chain`, the scene and each task are drawn from `seed`, each task in the state the previous one left.
    With a stored benchmark chain (tasks/chain_benchmark.py), the scene comes from `chain.scene_seed` and the tasks
    are its first `length` subtasks in order, each instruction (a paraphrase with `paraphrase`) from its subtask's
    seed, and the policy's seed from the subtask's and `seed` (the runs of one chain with other seeds differ only in
    the policy's own randomness, e.g. TriVLA's flow-matching noise); a subtask whose stored
    parameters cannot start in the state the policy left is attempted anyway, as CALVIN does, and
    `ChainResult.stored_task_feasible` says so.

    With `hold_check` (seconds) every success is followed by that hold (see `run_episode`) and the next task starts
    after it, so the chain differs from one without holds; `completed` counts its successes as the predicates first
    held (CALVIN's reading), and `completed_lasting` the tasks in a row whose success also held after the hold."""
    check_hold_check(hold_check)
    if chain is not None and not 1 <= length <= len(chain.subtasks):
        raise ValueError(f"length must be from 1 to the stored chain's {len(chain.subtasks)} subtasks, got {length}")
    if image_size is None and (policy.uses_images or video_path is not None):
        image_size = 224
    env = shared_env(image_size, scenario)
    hold = hold_steps(env, hold_check)
    rng = np.random.default_rng(seed)
    spec = sample_chain_scene(rng, env.layout()) if chain is None else benchmark_scene(chain.scene_seed, env.layout())
    recorder = _Recorder(False, video_path, env.action_space.control_rate_hz)
    result = ChainResult(seed, 0, [], completed_lasting=None if hold_check is None else 0)
    if chain is not None:
        result.chain_index, result.stored_task_feasible = chain.index, []
    used: set[str] = set()
    try:
        obs = env.reset(spec)
        for position in range(length):
            if chain is None:
                instance = next_chain_task(env.scene(), rng, used, paraphrase=paraphrase)
                if instance is None:
                    result.reason = "no task's preconditions hold (chain generator)"
                    break
                used.add(instance.task)
                policy_seed = int(rng.integers(2**31))
            else:
                instance, stored_seed = subtask_instance(chain.subtasks[position], paraphrase=paraphrase)
                policy_seed = derive_seed(stored_seed, seed) % 2**31
                result.stored_task_feasible.append(instance.params in get_task(instance.task).candidates(env.scene()))
            sub, obs = _run_subtask(
                env, obs, policy, instance, policy_seed, max_steps or get_task(instance.task).max_steps,
                recorder, hold=hold
            )
            result.subtasks.append(sub)
            if not sub.success:
                result.reason = f"{instance.task}: {sub.reason}"
                break
            if sub.lasted and result.completed_lasting == result.completed:
                result.completed_lasting += 1
            result.completed += 1
            if sub.reason:  # a success whose hold check failed in the simulation: the chain cannot go on
                result.reason = f"{instance.task}: {sub.reason}"
                break
        recorder.add(obs, None)
    except Exception as error:  # noqa: BLE001 - as for episodes: a failure with its reason
        _log.warning("chain seed %d failed: %s", seed, error)
        result.reason = f"{type(error).__name__}: {error}"
    try:
        recorder.finish()
    except Exception as error:  # noqa: BLE001
        _log.warning("could not write video %s: %s", video_path, error)
    return result
