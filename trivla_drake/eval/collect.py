"""`collect`: roll out the scripted oracle and write its successful episodes as a LeRobot dataset.

Attempt a of task T uses the seed `derive_seed(seed, T, a)`. Each task gets attempts 0, 1, 2, ...
until it has `episodes_per_task` successes (at most `2 N + 5` attempts); failures are recorded in
`meta/trivla_collection.json` with their reasons and never written as episodes. Episodes are
committed one at a time in a fixed order, so a killed run leaves every finished episode readable,
and running the same command again resumes: attempts already committed or failed are skipped.

With a `perturbation` (e.g. DART's bursts: the registered perturbation "dart", eval/perturbations.py) the applied
actions are disturbed; the recorded actions stay the oracle's and each episode's metadata lists its disturbed
frames. The dataset keeps the latest run's config as meta/collect_config.yaml.
With `prelude_tasks` > 0 the oracle first completes 1 to `prelude_tasks` other tasks of a chain (drawn
per attempt), unrecorded, and the episode starts where they left the scene and the hand, as the later
tasks of a chain do (the episode start "chain_prelude", eval/episode_starts.py); each episode's metadata lists them.
"""

from __future__ import annotations

import itertools
import json
import logging
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import asdict
from pathlib import Path

import numpy as np

from trivla_drake.data.durable import atomic_write_text
from trivla_drake.data.lerobot_format import (
    ACTION_NOISE_KEY,
    EPISODE_TASK_KEY,
    PERTURBED_FRAMES_KEY,
    PRELUDE_KEY,
    vector_feature,
    video_feature,
)
from trivla_drake.data.lerobot_stats import image_stats
from trivla_drake.data.lerobot_writer import LeRobotWriter
from trivla_drake.eval.collect_config import CollectConfig
from trivla_drake.eval.rollout_runner import RolloutRunner
from trivla_drake.systems.action_executor import ACTION_NAMES, DEFAULT_ACTION_SPACE

_log = logging.getLogger(__name__)
STATE_NAMES = (
    [f"panda_joint{i}_position" for i in range(1, 8)]
    + ["panda_finger_joint1_position", "panda_finger_joint2_position"]
    + [f"panda_joint{i}_velocity" for i in range(1, 8)]
    + ["panda_finger_joint1_velocity", "panda_finger_joint2_velocity"]
)
TCP_POSE_NAMES = ["x", "y", "z", "qw", "qx", "qy", "qz"]
CAMERAS = {"static_rgb": "observation.images.static", "wrist_rgb": "observation.images.wrist"}
PROGRESS_FILE = "meta/trivla_collection.json"
# The latest run's CollectConfig as YAML (`trivla-drake collect --config` reads it).
CONFIG_FILE = "meta/collect_config.yaml"
STAGING = ".staging"


def dataset_features(image_size: int, fps: float) -> dict[str, dict]:
    """The features of our datasets (see info.json)."""
    return {
        CAMERAS["static_rgb"]: video_feature(image_size, image_size, fps),
        CAMERAS["wrist_rgb"]: video_feature(image_size, image_size, fps),
        "observation.state": vector_feature(STATE_NAMES),
        "observation.tcp_pose": vector_feature(TCP_POSE_NAMES),
        "action": vector_feature(list(ACTION_NAMES)),
    }


def _attempt(config: CollectConfig, task: str, attempt: int) -> dict:
    """Run one oracle attempt; on success stage its videos. Top level: runs in workers."""
    from trivla_drake.eval.episode import derive_seed, run_episode
    from trivla_drake.eval.episode_starts import make_episode_start
    from trivla_drake.tasks.oracle import OraclePolicy

    seed = derive_seed(config.seed, task, attempt)
    start = None
    if config.prelude_tasks:  # 1 to prelude_tasks tasks, drawn per attempt
        prelude = 1 + int(np.random.default_rng(derive_seed(seed, "prelude_tasks")).integers(config.prelude_tasks))
        start = make_episode_start("chain_prelude", tasks=prelude)
    result = run_episode(
        task, seed, OraclePolicy(), image_size=config.image_size, keep_trajectory=True,
        perturbation=config.disturbance(), start=start,
    )
    out = {"task": task, "attempt": attempt, **result.to_dict()}
    if not result.success:
        return out
    from trivla_drake.data.video import write_video

    trajectory = result.trajectory
    for obs_key in CAMERAS:
        if len(trajectory.images.get(obs_key, ())) != len(trajectory):
            raise RuntimeError(f"{task} attempt {attempt}: {len(trajectory.images.get(obs_key, ()))} {obs_key} "
                               f"frames for {len(trajectory)} recorded steps")
    # Encoded here, returned as bytes: a worker on another machine of a cluster cannot write into the dataset folder.
    out["videos"], out["video_stats"] = {}, {}
    with tempfile.TemporaryDirectory(prefix="trivla-attempt-") as folder:
        for obs_key, feature in CAMERAS.items():
            frames = np.stack(trajectory.images[obs_key])
            path = Path(folder) / f"{obs_key}.mp4"
            write_video(path, frames, DEFAULT_ACTION_SPACE.control_rate_hz, config.video_codec)
            out["videos"][feature] = path.read_bytes()
            out["video_stats"][feature] = image_stats(frames)
    out["frames"] = {
        "observation.state": np.stack(trajectory.states),
        "observation.tcp_pose": np.stack(trajectory.tcp_poses),
        "action": np.stack(trajectory.actions),
    }
    out["perturbed_frames"] = [i for i, p in enumerate(trajectory.perturbed) if p]
    return out


class _Progress:
    """meta/trivla_collection.json: the latest run's settings (`config`), every run's that differed from the
    one before (`runs`: a folder resumed with, e.g., prelude_tasks holds episodes of both kinds), and every
    failed attempt (with its reason)."""

    def __init__(self, root: Path, config: CollectConfig):
        self.path = root / PROGRESS_FILE
        self.failed: dict[str, dict[str, str]] = {}
        self.runs: list[dict] = []
        if self.path.is_file():
            saved = json.loads(self.path.read_text())
            for key in ("seed", "image_size"):
                if saved["config"][key] != getattr(config, key):
                    raise ValueError(
                        f"{root} was collected with {key} {saved['config'][key]}, not {getattr(config, key)}: "
                        "use the same settings to resume, or another --out"
                    )
            self.failed = saved.get("failed", {})
            self.runs = saved.get("runs", [saved["config"]])
        if not self.runs or self.runs[-1] != asdict(config):
            self.runs.append(asdict(config))
        self.config = config

    def add_failure(self, task: str, attempt: int, reason: str) -> None:
        self.failed.setdefault(task, {})[str(attempt)] = reason
        self.save()

    def save(self) -> None:
        state = {"config": asdict(self.config), "runs": self.runs, "failed": self.failed}
        atomic_write_text(self.path, json.dumps(state, indent=2))


def collect(config: CollectConfig, *, progress: bool = True) -> dict:
    """Collect (or resume collecting) the dataset; returns a summary."""
    from tqdm import tqdm

    config.validate()
    root = Path(config.out)
    fps = DEFAULT_ACTION_SPACE.control_rate_hz
    writer = LeRobotWriter(root, fps=fps, features=dataset_features(config.image_size, fps), robot_type="panda")
    state = _Progress(root, config)
    state.save()
    from trivla_drake.config_io import save_config

    save_config(config, root / CONFIG_FILE)
    shutil.rmtree(root / STAGING, ignore_errors=True)  # videos of attempts that were never committed
    done: dict[str, set[int]] = {t: set() for t in config.tasks}
    for row in writer.episode_rows():
        if row.get(EPISODE_TASK_KEY) in done:
            done[row[EPISODE_TASK_KEY]].add(int(row["trivla/attempt"]))
    target = config.episodes_per_task * len(config.tasks)
    bar = tqdm(total=target, initial=sum(min(len(v), config.episodes_per_task) for v in done.values()),
               desc="collect", unit="ep", disable=not progress)
    try:
        with RolloutRunner(config.workers, config.ray_address) as runner:
            ran = True
            while ran:  # until a batch has no attempts left to run
                ran = False
                batch = _next_batch(config, done, state.failed)
                for result in runner.map_ordered(_attempt_job, config, batch, describe=_describe_attempt):
                    ran = True
                    _commit(writer, state, config, result)
                    if result["success"]:
                        done[result["task"]].add(result["attempt"])
                        bar.update(1)
    finally:
        bar.close()
    shutil.rmtree(root / STAGING, ignore_errors=True)
    per_task = {t: len(done[t]) for t in config.tasks}
    short = {t: n for t, n in per_task.items() if n < config.episodes_per_task}
    return {
        "out": str(root),
        "episodes": writer.num_episodes,
        "frames": writer.num_frames,
        "per_task": per_task,
        "failed_attempts": {t: len(v) for t, v in state.failed.items() if t in per_task},
        "short_tasks": short,
    }


def _next_batch(config: CollectConfig, done: dict[str, set[int]], failed: dict[str, dict]) -> Iterator[tuple[str, int]]:
    """The next attempts to run: for each task still short of episodes, as many new attempts as it
    needs, interleaved across tasks (so a partial dataset stays balanced). Drawn as they run (the attempts done and
    failed are read now), never listed up front."""
    per_task = [_fresh_attempts(task, config.episodes_per_task - len(done[task]), config.max_attempts(),
                                done[task] | {int(a) for a in failed.get(task, {})}) for task in config.tasks]
    skipped = object()
    for rank in itertools.zip_longest(*per_task, fillvalue=skipped):
        yield from (attempt for attempt in rank if attempt is not skipped)


def _fresh_attempts(task: str, need: int, max_attempts: int, tried: set[int]) -> Iterator[tuple[str, int]]:
    """(task, attempt) of the first `need` attempts below `max_attempts` not in `tried`."""
    fresh = (attempt for attempt in range(max_attempts) if attempt not in tried)
    return ((task, attempt) for attempt in itertools.islice(fresh, max(need, 0)))


def _attempt_job(config: CollectConfig, job: tuple[str, int]) -> dict:
    """`_attempt` of one (task, attempt); top level: runs in workers."""
    return _attempt(config, *job)


def _describe_attempt(job: tuple[str, int]) -> str:
    return f"collect: {job[0]} attempt {job[1]}"


def _commit(writer: LeRobotWriter, state: _Progress, config: CollectConfig, result: dict) -> None:
    """Record one attempt's result: a failure in the progress file, a success as the dataset's next episode (its
    videos staged in the dataset folder, then committed with its rows atomically)."""
    task, attempt = result["task"], result["attempt"]
    if not result["success"]:
        state.add_failure(task, attempt, result["reason"])
        return
    staging = Path(config.out) / STAGING
    staging.mkdir(parents=True, exist_ok=True)
    videos = {}
    for feature, data in result["videos"].items():
        videos[feature] = staging / f"{task}-{attempt:04d}-{feature.rsplit('.', 1)[-1]}.mp4"
        videos[feature].write_bytes(data)
    writer.add_episode(
        result["frames"],
        result["instruction"],
        videos={feature: str(path) for feature, path in videos.items()},
        video_stats=result["video_stats"],
        extra={
            EPISODE_TASK_KEY: task,
            "trivla/attempt": attempt,
            "trivla/seed": result["seed"],
            "trivla/params": list(result["params"]),
            # Every setting's column on every episode (EPISODE_COLUMN_DEFAULTS where unused): one schema.
            PERTURBED_FRAMES_KEY: result["perturbed_frames"],  # empty without a disturbance
            ACTION_NOISE_KEY: config.action_noise(),
            PRELUDE_KEY: list(result.get("prelude") or ()),
        },
    )
