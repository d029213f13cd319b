"""Where a policy's gripper first closes in closed loop, against the block the instruction names.

Lift, place in bowl and stack start with a grasp of the named block; the block is 4.5 cm wide and
the open gripper 8 cm, so a grasp holds only when the gripper closes within about 1.5 cm of the
block's centre (x, y) and low enough for the finger pads to reach its sides. For each episode this
reports where the gripper first closed: its x-y distance to the named block, whether another block
was nearer, its height; and, for a model with an instruction grounding, where the grounding put its
sub-goal on the first observation and on the observation the closing chunk was planned from. The
two separate a grounding that misses the block from a policy that misses its own sub-goal.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

GRASP_TASKS = ("lift_block", "stack_block", "place_in_bowl")  # each begins with a grasp of params[0]


@dataclass
class GraspRow:
    """One episode. Distances are in x-y, in metres; None where the gripper never closed or the model
    has no grounding."""

    task: str
    seed: int
    instruction: str
    success: bool
    close_step: int | None = None  # the first control step commanding the gripper closed
    closes: int = 0  # how often the gripper was commanded closed from open (a retried grasp counts again)
    close_to_block_m: float | None = None  # tool-centre point to the named block's centre when it closes
    nearest_block_named: bool | None = None  # the named block is the nearest one when it closes
    close_height_m: float | None = None  # the tool-centre point's height when it closes
    first_subgoal_to_block_m: float | None = None  # the grounding's sub-goal on the first observation
    close_subgoal_to_block_m: float | None = None  # ... on the observation the closing chunk was planned from
    close_to_subgoal_m: float | None = None  # tool-centre point to that sub-goal when it closes
    # The hand's yaw when it closes against the named block's faces (as the scene starts), in degrees
    # modulo a quarter turn: in [-45, 45); near +-45 the fingers come down on the block's corners.
    close_yaw_error_deg: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


class _SubgoalRecorder:
    """Wraps a TriVLA harness policy: passes every call through and records, per chunk, the step it
    starts at and the grounding's sub-goal [m] for the same observation (a second System 2 pass per
    chunk: a diagnostic's cost, not the policy's)."""

    def __init__(self, policy, grounded: bool) -> None:
        self._policy, self._grounded = policy, grounded
        self.name, self.uses_images, self.privileged = policy.name, policy.uses_images, policy.privileged
        self.chunks: list[tuple[int, np.ndarray | None]] = []
        self._steps = 0

    def reset(self, instruction: str, seed: int) -> None:
        self.chunks.clear()
        self._steps = 0
        self._policy.reset(instruction, seed)

    def act(self, observation: dict) -> np.ndarray:
        subgoal = None
        if self._grounded:
            subgoal = self._policy.model.predict_subgoal(
                observation["static_rgb"], observation["wrist_rgb"], observation["instruction"], observation["state"])
        rows = np.atleast_2d(self._policy.act(observation))
        self.chunks.append((self._steps, subgoal))
        self._steps += len(rows)
        return rows

    def subgoal_at(self, step: int) -> np.ndarray | None:
        """The sub-goal of the chunk that step `step` was executed from."""
        starts = [start for start, _ in self.chunks]
        return self.chunks[int(np.searchsorted(starts, step, side="right")) - 1][1] if self.chunks else None


def _xy(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a)[:2] - np.asarray(b)[:2]))


def grasp_report(policy, episodes_per_task: int = 6, seed: int = 1000,
                 tasks: tuple[str, ...] = GRASP_TASKS, max_steps: int | None = None) -> list[GraspRow]:
    """Runs `episodes_per_task` episodes of each of `tasks` (seeds `seed`, `seed` + 1, ...: 1000 on
    are scenes the demonstrations never saw) with `policy` (a harness policy; a TriVLA one with a
    grounding also gets its sub-goals recorded) and reports where its gripper first closed.
    `max_steps` cuts each episode short (None: the task's own limit)."""
    from trivla_drake.data.subgoals import quaternion_yaw
    from trivla_drake.eval.episode import run_episode, shared_env
    from trivla_drake.tasks.scene import yaw_to_faces_deg
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    if episodes_per_task < 1:
        raise ValueError(f"episodes_per_task must be >= 1, got {episodes_per_task}")
    unknown = [t for t in tasks if t not in GRASP_TASKS]
    if unknown:
        raise ValueError(f"tasks must be among {', '.join(GRASP_TASKS)} (each begins with a grasp); got {unknown}")
    model = getattr(policy, "model", None)
    grounded = model is not None and getattr(model.policy, "grounding", None) is not None
    recorder = _SubgoalRecorder(policy, grounded)
    rows = []
    for task in tasks:
        for k in range(episodes_per_task):
            episode_seed = seed + k
            result = run_episode(task, episode_seed, recorder, keep_trajectory=True, max_steps=max_steps)
            # The initial blocks: the scene run_episode drew from the same seed (the trajectory keeps no scene).
            spec, instance = sample_task_instance(get_task(task), np.random.default_rng(episode_seed),
                                                  shared_env(224).layout())
            if instance.instruction != result.instruction:
                raise RuntimeError(f"{task} seed {episode_seed}: the scene drawn again is not the episode's "
                                   f"({instance.instruction!r} against {result.instruction!r})")
            blocks = {colour: np.asarray(b.position) for colour, b in spec.blocks.items()}
            named_colour = result.params[0]
            named = blocks[named_colour]
            actions = np.asarray(result.trajectory.actions).reshape(-1, 7)
            closed = np.flatnonzero(actions[:, 6] <= 0.0)
            row = GraspRow(task, episode_seed, result.instruction, bool(result.success))
            row.closes = count_closes(actions[:, 6])
            first_subgoal = recorder.chunks[0][1] if recorder.chunks else None
            if first_subgoal is not None:
                row.first_subgoal_to_block_m = _xy(first_subgoal, named)
            if closed.size:
                step = int(closed[0])
                pose = np.asarray(result.trajectory.tcp_poses[step])
                tcp = pose[:3]
                distances = {colour: _xy(tcp, position) for colour, position in blocks.items()}
                row.close_step = step
                row.close_to_block_m = distances[named_colour]
                row.nearest_block_named = min(distances, key=distances.get) == named_colour
                row.close_height_m = float(tcp[2])
                row.close_yaw_error_deg = yaw_to_faces_deg(quaternion_yaw(pose[3:7]), spec.blocks[named_colour].yaw)
                subgoal = recorder.subgoal_at(step)
                if subgoal is not None:
                    row.close_subgoal_to_block_m = _xy(subgoal, named)
                    row.close_to_subgoal_m = _xy(tcp, subgoal)
            rows.append(row)
    return rows


def count_closes(gripper: np.ndarray) -> int:
    """How often a gripper command sequence (> 0 open, <= 0 closed; the hand starts open) closes."""
    closed = np.asarray(gripper) <= 0.0
    return int(closed[:1].sum() + np.sum(closed[1:] & ~closed[:-1]))


def grasp_summary(rows: list[GraspRow]) -> dict:
    """Counts and medians over the episodes (distances in cm; None where nothing was measured)."""
    closed = [r for r in rows if r.close_step is not None]

    def median(key):
        kept = [getattr(r, key) for r in rows if getattr(r, key) is not None]
        return round(100 * float(np.median(kept)), 2) if kept else None

    return {
        "episodes": len(rows),
        "successes": sum(r.success for r in rows),
        "closed": len(closed),
        "closed_again": sum(r.closes > 1 for r in rows),
        "successes_after_closing_again": sum(r.closes > 1 and r.success for r in rows),
        "nearest_block_named": sum(bool(r.nearest_block_named) for r in closed),
        "closed_within_1_5_cm": sum(r.close_to_block_m < 0.015 for r in closed),
        "closed_within_3_cm": sum(r.close_to_block_m < 0.03 for r in closed),
        "median_close_to_block_cm": median("close_to_block_m"),
        "median_close_height_cm": median("close_height_m"),
        "median_first_subgoal_to_block_cm": median("first_subgoal_to_block_m"),
        "median_close_subgoal_to_block_cm": median("close_subgoal_to_block_m"),
        "median_close_to_subgoal_cm": median("close_to_subgoal_m"),
        "median_abs_close_yaw_error_deg": (round(float(np.median([abs(r.close_yaw_error_deg) for r in closed])), 1)
                                           if closed else None),
        "closed_within_15_deg": sum(abs(r.close_yaw_error_deg) <= 15.0 for r in closed),
    }


def format_grasp_report(rows: list[GraspRow]) -> str:
    """A Markdown table of the episodes and a summary line."""
    lines = [
        "| task | seed | success | closes at step | closes | to named block [cm] | named block nearest | height [cm] "
        "| yaw to the block's faces [deg] | sub-goal to block, first / at close [cm] | to sub-goal [cm] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        def cm(value):
            return "-" if value is None else f"{100 * value:.1f}"
        nearest = "-" if r.nearest_block_named is None else ("yes" if r.nearest_block_named else "no")
        lines.append(f"| {r.task} | {r.seed} | {'yes' if r.success else 'no'} | "
                     f"{'never' if r.close_step is None else r.close_step} | {r.closes} | {cm(r.close_to_block_m)} | {nearest} | "
                     f"{cm(r.close_height_m)} | {'-' if r.close_yaw_error_deg is None else f'{r.close_yaw_error_deg:+.0f}'} | "
                     f"{cm(r.first_subgoal_to_block_m)} / {cm(r.close_subgoal_to_block_m)} | "
                     f"{cm(r.close_to_subgoal_m)} |")
    s = grasp_summary(rows)

    def median(key):
        return "-" if s[key] is None else f"{s[key]:.1f}"

    lines.append("")
    lines.append(
        f"{s['successes']}/{s['episodes']} succeed; the gripper closes in {s['closed']} (again after opening in "
        f"{s['closed_again']}, of which {s['successes_after_closing_again']} succeed); at its first close it is "
        f"nearest the named block in "
        f"{s['nearest_block_named']}, within 1.5 cm of it in {s['closed_within_1_5_cm']} and within 3 cm in "
        f"{s['closed_within_3_cm']}; medians: {median('median_close_to_block_cm')} cm from the block "
        f"at {median('median_close_height_cm')} cm height, the hand's yaw within 15 degrees of the block's faces in "
        f"{s['closed_within_15_deg']} (median {median('median_abs_close_yaw_error_deg')} degrees off); the grounding's sub-goal "
        f"{median('median_first_subgoal_to_block_cm')} cm from the block first, "
        f"{median('median_close_subgoal_to_block_cm')} cm when the closing chunk was planned, "
        f"the gripper {median('median_close_to_subgoal_cm')} cm from that sub-goal")
    return "\n".join(lines)
