"""Does System 1's instruction grounding find the block an instruction names?

For each of a few unseen scenes of `lift_block`, the instruction is asked once per block colour
("pick up the red block", "... green ...", ...): the grounding's sub-goal (the next gripper event,
a grasp of the named block) should lie nearest to the block named, and close to it. A grounding
that ignores the colour word scores about 1/3, the share of one block among three, however close
it comes to *some* block (results/instruction_grounding).

Then the same scenes along the expert's approach: the oracle drives the arm to the grasp of the
named block, and every few steps until the gripper closes the grounding is asked again for every
colour. The errors are reported by how far the tool-centre point still is from the block approached:
a grasp needs the sub-goal within about 1.5 cm when the gripper is near. The expert approaches from
straight above, so a grounding could score well on the block approached by copying the tcp's x-y;
the other colours' queries catch that (the gripper is then far from the block asked for, as a
learned policy's gripper is when it heads the wrong way).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from trivla_drake.tasks.scene import BLOCK_COLORS, hand_yaw, yaw_to_faces_deg

CHECK_TASK = "lift_block"  # its first gripper event is the grasp of the block the instruction names
# Bands of the tcp's 3-D distance to the named block [m] along the approach: (name, lower, upper).
APPROACH_BANDS = (("far", 0.15, float("inf")), ("mid", 0.05, 0.15), ("near", 0.0, 0.05))
APPROACH_EVERY = 4  # control steps between two queries along the approach
YAW_TOLERANCE_DEG = 15.0  # a yaw error a grasp of a 4.5 cm block in the 8 cm open gripper still takes


@dataclass
class GroundingCheck:
    """`hits` of `queries` sub-goals lie nearest (in x, y) to the block named; `median_error_m` is the
    median x-y distance to that block [m]; `chance` the hit rate of a colour-blind guess."""

    scenes: int
    queries: int
    hits: int
    median_error_m: float
    chance: float
    # Along the approach of `driver` (None when not measured), per band of the tcp's distance to the block
    # approached (APPROACH_BANDS): queries, hits and median x-y error [m] (None: no query) when asking
    # for the block approached ("approached") and for the other blocks ("other").
    approach: dict[str, dict[str, dict]] | None = None
    # For a grounding that predicts the grasp's yaw (policy.subgoal_yaw), along the approach, per band:
    # queries, how many are within YAW_TOLERANCE_DEG of the approached block's faces (a guess: a third)
    # and the median |error| [deg] (modulo a quarter turn, so at most 45). None without it. Its read-out
    # does not read the instruction: the wrist view near the block shows which one.
    approach_yaw: dict[str, dict] | None = None
    driver: str | None = None  # whose trajectories the approach follows ("oracle", or a policy's name)

    def to_dict(self) -> dict:
        return asdict(self)


def ask_every_colour(model, observation: dict, instruction: str, named: str,
                     blocks: dict[str, np.ndarray]) -> list[tuple[str, float, bool, float | None]]:
    """The grounding asked once per block colour (`named` in `instruction` replaced by it), on one
    observation (its images and state): per colour, (colour, x-y error of the sub-goal to that
    colour's block in `blocks` [m], whether that block is the sub-goal's nearest, the grounding's yaw
    [rad] with policy.subgoal_yaw, else None)."""
    answers = []
    for colour in BLOCK_COLORS:
        subgoal, yaw = model.predict_grounding(observation["static_rgb"], observation["wrist_rgb"],
                                               instruction.replace(named, colour), observation["state"])
        distance = {c: float(np.linalg.norm((subgoal - p)[:2])) for c, p in blocks.items()}
        answers.append((colour, distance[colour], min(distance, key=distance.get) == colour, yaw))
    return answers


class _ApproachProbe:
    """A harness policy: the oracle (or `driver`, a harness policy) drives, and until its gripper first
    closes the grounding is asked for every block colour every `every` steps (every chunk of a driver
    that plans chunks). Records (tcp distance to the block approached [m],
    whether the colour asked is that block's, x-y error to the block asked [m], whether the sub-goal
    is nearest the block asked). An error inside the model is kept and raised after the episode (the
    runner would count it as the episode's failure and go on)."""

    name, uses_images, privileged = "oracle+grounding", True, True

    def __init__(self, model, every: int, driver=None) -> None:
        from trivla_drake.tasks.oracle import OraclePolicy

        self._model, self._every = model, every
        self._driver = OraclePolicy() if driver is None else driver
        self.records: list[tuple[float, bool, float, bool]] = []
        # (tcp distance [m], the grounding's yaw error [deg], the hand's own yaw error [deg]), with a yaw
        self.yaw_records: list[tuple[float, float, float]] = []
        self.error: Exception | None = None
        self._steps, self._closed = 0, False

    def reset(self, instruction: str, seed: int) -> None:
        self._driver.reset(instruction, seed)
        self._steps, self._closed = 0, False

    def act(self, observation: dict) -> np.ndarray:
        # A learned driver answers a chunk per call: then every call is asked (it is one every chunk).
        rows = np.atleast_2d(np.asarray(self._driver.act(observation)))
        due = len(rows) > 1 or self._steps % self._every == 0
        if not self._closed and due and self.error is None:
            try:
                named, scene = observation["privileged"]["task"].params[0], observation["privileged"]["scene"]
                blocks = {colour: np.asarray(scene.block_position(colour)) for colour in BLOCK_COLORS}
                reach = float(np.linalg.norm(np.asarray(observation["tcp_pose"])[:3, 3] - blocks[named]))
                for colour, error, hit, yaw in ask_every_colour(self._model, observation, observation["instruction"],
                                                                named, blocks):
                    self.records.append((reach, colour == named, error, hit))
                    if colour == named and yaw is not None:
                        faces = scene.block_yaw(named)
                        hand = hand_yaw(np.asarray(observation["tcp_pose"]))
                        self.yaw_records.append((reach, yaw_to_faces_deg(yaw, faces), yaw_to_faces_deg(hand, faces)))
            except Exception as error:  # noqa: BLE001 - raised by approach_errors after the episode
                self.error = error
        self._closed = self._closed or bool(np.any(rows[:, 6] <= 0.0))
        self._steps += len(rows)
        return rows if len(rows) > 1 else rows[0]


def approach_errors(model, scenes: int, seed: int, every: int = APPROACH_EVERY, driver=None
                    ) -> tuple[list[tuple[float, bool, float, bool]], list[tuple[float, float, float]]]:
    """Every `every` steps of the oracle's approach (or, with `driver`, a harness policy's: every chunk
    it plans), until it first closes the gripper, in `scenes`
    lift_block scenes from `seed` on, one record per block colour asked: (tcp distance to the block
    approached [m], asked for that block, x-y error of the sub-goal to the block asked [m], the
    sub-goal nearest the block asked); and, for a grounding with a yaw (policy.subgoal_yaw), one per
    query of the block approached: (tcp distance [m], yaw error to its faces [deg], the hand's own yaw
    error to them [deg]); else none."""
    from trivla_drake.eval.episode import run_episode

    probe = _ApproachProbe(model, every, driver)
    for k in range(scenes):
        run_episode(CHECK_TASK, seed + k, probe)
        if probe.error is not None:
            raise probe.error
    return probe.records, probe.yaw_records


def grounding_check(model, scenes: int = 10, seed: int = 1000, approach: bool = True, driver=None) -> GroundingCheck:
    """Asks `model`'s grounding (a TriVLA with `policy.instruction_grounding`) for every block colour
    in `scenes` scenes of lift_block drawn from seeds `seed`, `seed` + 1, ... (1000 on: scenes the
    demonstrations, collected from seed 0, never showed), and with `approach`, along the oracle's
    approach in the same scenes; with `driver` (a harness policy, e.g. a TriVLAHarnessPolicy), along
    its trajectories instead, which are what a grounding guides in closed loop."""
    from trivla_drake.eval.episode import shared_env
    from trivla_drake.tasks.suite import get_task, sample_task_instance

    if scenes < 1:
        raise ValueError(f"scenes must be >= 1, got {scenes}")
    if model.policy.grounding is None:
        raise ValueError("the model has no instruction grounding (policy.instruction_grounding is off): "
                         "train one with `train --stage policy --grounding-weight W`")
    env = shared_env(model.image_size)
    hits, errors = 0, []
    for k in range(scenes):
        spec, instance = sample_task_instance(get_task(CHECK_TASK), np.random.default_rng(seed + k), env.layout())
        named = instance.params[0]
        observation = env.reset(spec)
        scene = env.scene()
        blocks = {colour: np.asarray(scene.block_position(colour)) for colour in BLOCK_COLORS}
        for _, error, hit, _ in ask_every_colour(model, observation, instance.instruction, named, blocks):
            hits += hit
            errors.append(error)
    check = GroundingCheck(scenes=scenes, queries=len(errors), hits=hits,
                           median_error_m=float(np.median(errors)), chance=1.0 / len(BLOCK_COLORS))

    if approach:
        records, yaw_records = approach_errors(model, scenes, seed, driver=driver)
        check.driver = "oracle" if driver is None else getattr(driver, "name", type(driver).__name__)
        records = np.asarray(records, dtype=float).reshape(-1, 4)
        check.approach = {}
        for band, low, high in APPROACH_BANDS:
            inside = records[(records[:, 0] >= low) & (records[:, 0] < high)]
            check.approach[band] = {}
            for which, rows in (("approached", inside[inside[:, 1] == 1]), ("other", inside[inside[:, 1] == 0])):
                check.approach[band][which] = {
                    "queries": int(len(rows)), "hits": int(rows[:, 3].sum()),
                    "median_error_m": float(np.median(rows[:, 2])) if len(rows) else None}
        if yaw_records:
            check.approach_yaw = _yaw_bands(np.asarray(yaw_records, dtype=float))
    return check


def _yaw_bands(records: np.ndarray) -> dict[str, dict]:
    """Per band, the yaw queries, how many are within tolerance and their median |error|; and the same
    counts split by whether the hand itself was within tolerance of the faces ("hand_right" /
    "hand_off"): a read-out that takes the yaw from the wrist view's own turn is right only with the
    hand already right."""
    bands = {}
    for band, low, high in APPROACH_BANDS:
        inside = records[(records[:, 0] >= low) & (records[:, 0] < high)]
        errors, hand_right = np.abs(inside[:, 1]), np.abs(inside[:, 2]) <= YAW_TOLERANCE_DEG
        right = errors <= YAW_TOLERANCE_DEG
        bands[band] = {"queries": int(len(errors)), "within_tolerance": int(right.sum()),
                       "median_error_deg": float(np.median(errors)) if len(errors) else None,
                       "hand_right": [int(right[hand_right].sum()), int(hand_right.sum())],
                       "hand_off": [int(right[~hand_right].sum()), int((~hand_right).sum())]}
    return bands


def format_grounding_check(check: GroundingCheck) -> str:
    """One line for the terminal."""
    return (f"instruction grounding on {check.scenes} unseen lift_block scenes: the sub-goal is nearest the "
            f"named block in {check.hits}/{check.queries} queries ({check.hits / check.queries:.2f}; a colour-blind "
            f"guess {check.chance:.2f}), median {100 * check.median_error_m:.1f} cm from it"
            + _format_approach(check) + _format_yaw(check))


def _format_yaw(check: GroundingCheck) -> str:
    if check.approach_yaw is None:
        return ""
    lines = ["", f"its yaw along the approach, against the approached block's faces (within {YAW_TOLERANCE_DEG:.0f} "
                 "degrees; a guess: a third; median error; then split by whether the hand's own yaw was within "
                 f"{YAW_TOLERANCE_DEG:.0f} degrees of them):"]
    for band, row in check.approach_yaw.items():
        error = "-" if row["median_error_deg"] is None else f"{row['median_error_deg']:.0f} degrees"
        (right, of_right), (off, of_off) = row["hand_right"], row["hand_off"]
        lines.append(f"  {band}: {row['within_tolerance']}/{row['queries']}, {error}; hand turned right "
                     f"{right}/{of_right}, hand off {off}/{of_off}")
    return "\n".join(lines)


def _format_approach(check: GroundingCheck) -> str:
    if check.approach is None:
        return ""
    whose = "the oracle's approach" if check.driver == "oracle" else f"the approach of policy {check.driver}"
    lines = ["", f"along {whose} (tcp distance to the block approached: asking for that block / "
                 "for another; nearest the block asked, median x-y error):"]
    for band, low, high in APPROACH_BANDS:
        where = f"> {100 * low:.0f} cm" if high == float("inf") else f"{100 * low:.0f}-{100 * high:.0f} cm"
        parts = []
        for which in ("approached", "other"):
            row = check.approach[band][which]
            error = "-" if row["median_error_m"] is None else f"{100 * row['median_error_m']:.1f} cm"
            parts.append(f"{row['hits']}/{row['queries']}, {error}")
        lines.append(f"  {band} ({where}): {parts[0]} / {parts[1]}")
    return "\n".join(lines)
