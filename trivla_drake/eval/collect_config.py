"""`CollectConfig`, what `collect` writes (loadable from YAML: `trivla-drake collect --config FILE --set k=v`; a
dataset keeps its own as meta/collect_config.yaml)."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc
from typing import Optional

from trivla_drake.eval.evaluate_config import check_episode_count
from trivla_drake.eval.plugin_config import PluginConfig
from trivla_drake.tasks.chains import CHAIN_LENGTH
from trivla_drake.tasks.run_settings import check_run_settings
from trivla_drake.tasks.suite import TASK_NAMES

MAX_PRELUDE_TASKS = CHAIN_LENGTH - 1


@dc.dataclass
class CollectConfig:
    """What `collect` writes."""

    # Dataset folder (created, or resumed if it holds an earlier run's dataset).
    out: str = ""
    # Successful episodes wanted per task.
    episodes_per_task: int = 50
    # Task names (all by default).
    tasks: list[str] = dc.field(default_factory=lambda: list(TASK_NAMES))
    # Base seed.
    seed: int = 0
    # Local worker processes (1: in this process; more: a local Ray with that many, started and stopped by the
    # command). Ignored with ray_address.
    workers: int = 1
    # An existing Ray cluster to run on (e.g. 'ray://head:10001' or 'auto'; None: $RAY_ADDRESS if set, else
    # local). The results are the same as a serial run's, whatever the cluster's size.
    ray_address: Optional[str] = None
    # Camera image size [px] (square).
    image_size: int = 224
    # Codec of the camera videos (data/video.py): "mpeg4" (MPEG-4 Part 2, OpenCV's), "h264" (libx264) or "av1"
    # (libsvtav1, lerobot's default), yuv420p mp4. One dataset holds one codec: a resumed one must keep its own.
    video_codec: str = "mpeg4"
    # A registered perturbation of the applied actions (eval/perturbations.py; name "": clean demonstrations), e.g.
    # DART's bursts {name: dart, settings: {scale: 1.0}} (scale: a multiple of the default burst rate, 1 = a burst
    # about every 17 steps). The recorded actions stay the oracle's; recorded per episode, so a resumed run may
    # change it (episodes started from then on get it).
    perturbation: PluginConfig = dc.field(default_factory=PluginConfig)
    # Before its task the oracle completes 1 to this many other tasks of a chain (drawn per attempt),
    # unrecorded, so the episode starts where a chain's earlier tasks leave the scene and the hand
    # (0: from the start posture). Recorded per episode (PRELUDE_KEY, the tasks' names).
    prelude_tasks: int = 0

    def validate(self) -> None:
        """ValueError naming the flag or the dotted field of a setting that cannot run."""
        if not self.out:
            raise ValueError("--out is missing: the dataset folder to write (or resume)")
        check_episode_count(self.episodes_per_task, "--episodes-per-task")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise ValueError(f"--workers must be an integer >= 1, got {self.workers!r}")
        if self.image_size < 16 or self.image_size % 2:
            raise ValueError(f"image_size must be an even number >= 16, got {self.image_size}")
        if not self.tasks:
            raise ValueError("--tasks is empty")
        self.check_video_codec()
        self.disturbance()  # validates the perturbation
        if (isinstance(self.prelude_tasks, bool) or not isinstance(self.prelude_tasks, int)
                or not 0 <= self.prelude_tasks <= MAX_PRELUDE_TASKS):
            raise ValueError(f"prelude_tasks must be an integer from 0 to {MAX_PRELUDE_TASKS} (a chain has "
                             f"{MAX_PRELUDE_TASKS + 1} tasks), got {self.prelude_tasks!r}")
        check_run_settings(self.tasks, self.seed)

    def check_video_codec(self) -> None:
        """ValueError naming video_codec: a codec not in VIDEO_CODECS, one this PyAV build cannot encode, or
        another than the videos of the dataset at `out` already are in."""
        from trivla_drake.data.lerobot_format import dataset_video_codec
        from trivla_drake.data.video import video_encoder

        video_encoder(self.video_codec, "video_codec")
        held = dataset_video_codec(self.out)
        if held is not None and held != self.video_codec:
            raise ValueError(f"video_codec {self.video_codec!r}: {self.out} holds {held!r} video; one dataset holds "
                             f"one codec: resume it with video_codec {held!r} (--set video_codec={held}), or "
                             "choose another --out")

    def action_noise(self) -> float:
        """The DART scale of the perturbation (0: none or another kind): each episode's ACTION_NOISE_KEY column."""
        return float(self.perturbation.settings.get("scale", 1.0)) if self.perturbation.name == "dart" else 0.0

    def disturbance(self) -> Optional[object]:
        """The perturbation as a `Disturbance` (None: clean, also DART at scale 0); ValueError naming the field."""
        from trivla_drake.eval.perturbations import make_perturbation

        name = self.perturbation.name
        if not name:
            if self.perturbation.settings:
                raise ValueError(f"perturbation.settings {self.perturbation.settings} without a perturbation.name")
            return None
        if name == "dart" and self.action_noise() == 0:
            return None
        try:
            return make_perturbation(name, **self.perturbation.settings)
        except ValueError as error:  # also a setting the factory does not take (Registry.make)
            raise ValueError(f"perturbation ({name}): {error}") from None

    def max_attempts(self) -> int:
        return 2 * self.episodes_per_task + 5
