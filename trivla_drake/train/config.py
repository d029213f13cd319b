"""The training configuration: one dataclass for the three stages, saved with every checkpoint.

Stages (run in this order; each starts from the previous one's checkpoint with `init`):
  video   System 3 fine-tuned on the dataset's clips with eq. (1)
  vlm     System 2 pretrained on simulator-generated visual questions (next-token loss on answers)
  policy  System 1 trained with eq. (5) (flow matching), Systems 2 and 3 frozen, their features cached
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass
from typing import Any

from trivla_drake.nn.config import without_removed_fields

STAGES = ("video", "vlm", "policy")
GROUNDING_PHASES = ("joint", "bind", "follow")  # TrainConfig.grounding_phase

# Per-stage defaults for the fields left None (chosen for the `cpu` preset on a 2-core machine;
# see the measured step times in trivla_drake/train/README.md).
STAGE_DEFAULTS: dict[str, dict[str, Any]] = {
    "video": {"batch_size": 8, "lr": 1e-4, "steps": 3000},
    "vlm": {"batch_size": 8, "lr": 3e-4, "steps": 3000},
    "policy": {"batch_size": 32, "lr": 1e-4, "steps": 10000},
}

# Seeds `train` takes: numpy's generators take no negative seed, torch.manual_seed none above 64 bits.
SEEDS = range(0, 2**64)

# Fields that may differ between a run and the run it resumes (they do not change what is learned).
RESUMABLE_CHANGES = frozenset(
    {"steps", "checkpoint_every", "keep_checkpoints", "resume", "workers", "progress", "log_every", "threads",
     "cache_dir", "dist_timeout_minutes", "out", "data", "extra_data", "init", "vqa_eval_questions"}
)


# The `train` flags whose names are not the field's (`--` + the name with dashes); a test checks them
# against the parser.
FLAGS_NAMED_OTHERWISE = {
    "use_system2": "--no-system2",
    "use_system3": "--no-system3",
    "progress": "--no-progress",
    "grounding_carry_tasks": "--grounding-carry",
}
# Fields that no `train` flag sets (their defaults, or a preset's).
FIELDS_WITHOUT_FLAG = frozenset(
    {"weight_decay", "beta1", "static_camera", "wrist_camera", "feature_batch_size", "feature_seed",
     "vqa_scenes", "vqa_questions_per_scene", "vqa_eval_questions", "vqa_seed", "log_every", "dist_timeout_minutes"}
)
# Options of experiments that left the product (their code is at git tag `research-archive`), each at the value
# every run of the product had: a saved training config that lists one at that value loads (the field ignored);
# one that set it otherwise is refused, naming the field.
REMOVED_FIELDS: dict[str, Any] = {
    "fraction": 1.0, "gripper_event_weight": 1, "gripper_event_window_s": 1.0, "tcp_features": True,
    "vlm_loss_weighting": "token", "image_token_norm": False, "answer_weight": 1.0, "keep_normalization": False,
    "grounding_reads_tcp": False, "subgoal_noise": 0.0, "subgoal_yaw": False, "grounding_anchor_camera": (),
    "grounding_anchor_wrist_camera": (),
}


def flag_of(field_name: str) -> str | None:
    """The `train` flag that sets TrainConfig's `field_name`, or None."""
    if field_name in FIELDS_WITHOUT_FLAG:
        return None
    return FLAGS_NAMED_OTHERWISE.get(field_name, "--" + field_name.replace("_", "-"))


def named(field_name: str) -> str:
    """A field as errors name it: `lr (--lr)`, or the bare name where no flag sets it."""
    flag = flag_of(field_name)
    return f"{field_name} ({flag})" if flag else field_name


def default_cache_dir() -> str:
    """$XDG_CACHE_HOME/trivla_drake/train (default ~/.cache/trivla_drake/train)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "trivla_drake", "train")


@dataclass
class TrainConfig:
    """Everything a training run depends on. Fields left None get their stage's default in `resolved()`."""

    # Which system to train: "video" (System 3), "vlm" (System 2) or "policy" (System 1).
    stage: str
    # Output folder: checkpoints/step-XXXXXXXX/ (periodic), final/ (the last), log.jsonl, summary.json.
    out: str
    # LeRobot dataset folder (video and policy stages). For the vlm stage: an optional folder for the
    # generated visual-question set (default: a folder in `cache_dir` named by the generation settings).
    data: str | None = None
    # Policy stage: more LeRobot dataset folders trained on together with `data` (same state, action and
    # cameras; normalisation over all; an episode that two folders both hold is trained on once).
    extra_data: tuple[str, ...] = ()
    # Model preset (tiny, cpu, paper) of a fresh model; None: the --init checkpoint's preset, else "cpu".
    # Given together with `init`, it must match the checkpoint's preset.
    preset: str | None = None
    # Checkpoint folder to start from (the previous stage's final/); None: a fresh `preset` model.
    init: str | None = None
    # Optimizer steps in all (a resumed run continues up to this count). None: the stage's default.
    steps: int | None = None
    # Samples per process per step (the effective batch is batch_size x world size). None: stage default.
    batch_size: int | None = None
    # Peak learning rate of AdamW. None: the stage's default.
    lr: float | None = None
    # AdamW decoupled weight decay.
    weight_decay: float = 0.01
    # AdamW beta1.
    beta1: float = 0.9
    # AdamW beta2.
    beta2: float = 0.95
    # Linear warm-up steps from 0 to `lr` (capped at a tenth of `steps` for short runs).
    warmup_steps: int = 100
    # After warm-up the learning rate follows a cosine from `lr` down to lr * min_lr_ratio at `steps`.
    min_lr_ratio: float = 0.1
    # Gradient norm clipping (0 turns it off).
    grad_clip: float = 1.0
    # Write a checkpoint every this many steps (and always at the last step).
    checkpoint_every: int = 500
    # Periodic checkpoints kept on disk (older ones are deleted once a newer one is complete).
    keep_checkpoints: int = 2
    # Continue from the newest checkpoint in `out` (model, optimizer, step, data position, RNG states).
    resume: bool = False
    # Seed of everything random: fresh-model initialisation, data order, diffusion/flow noise.
    seed: int = 0
    # DataLoader worker processes per training process (0 loads in the training process).
    workers: int = 0
    # Keep System 2 (vision-language tokens) in the model; False is the Table 4 ablation "1+3".
    use_system2: bool = True
    # Keep System 3 (dynamics features) in the model; False is the Table 4 ablation "1+2".
    use_system3: bool = True
    # Folder for data made once and reused: decoded clips, the VQA set, cached System 2/3 features.
    # Entries are named by hashes of everything they depend on, so runs can share it. None: default_cache_dir().
    cache_dir: str | None = None
    # Dataset camera of System 2/3's static (third-person) view.
    static_camera: str = "observation.images.static"
    # Dataset camera of the wrist view.
    wrist_camera: str = "observation.images.wrist"
    # Policy stage: cache (and train on) every this-many-th frame of each episode.
    feature_stride: int = 1
    # Policy stage: dtype of cached System 2/3 features ("float16" halves the disk; "float32" is exact).
    feature_dtype: str = "float16"
    # Policy stage: frames per batch when computing the cached features.
    feature_batch_size: int = 16
    # Policy stage: seed of System 3's noise latents for the cached features (part of the cache key).
    feature_seed: int = 0
    # Video stage: a clip (current frame + num_frames-1 future frames) spans about this many seconds.
    clip_seconds: float = 1.0
    # Video stage: frames between clip frames; None: round(fps * clip_seconds / (num_frames - 1)).
    future_stride: int | None = None
    # vlm stage: simulator scenes rendered for the visual-question set.
    vqa_scenes: int = 500
    # vlm stage: questions asked about each scene.
    vqa_questions_per_scene: int = 8
    # vlm stage: held-out questions scored at the end of the run (multiple-choice accuracy); 0 skips it.
    vqa_eval_questions: int = 400
    # vlm stage: seed of the scene sampling and question choice (part of the VQA set's key).
    vqa_seed: int = 0
    # vlm stage: weight of the dense loss of System 2's block head (which blocks each image token's
    # cell shows, from the renderer's label images; `VisionLanguageConfig.dense_classes`); a run from
    # a checkpoint without the head adds one. 0: no dense loss (the shipped recipe).
    dense_weight: float = 0.0
    # vlm stage, with dense_weight: sub-cells per side of each token's cell the block head tells apart
    # (`VisionLanguageConfig.dense_subcells`); a starting head with others is replaced by a fresh one.
    # None: as the --init model has them (1 for a fresh model or one without a head).
    dense_subcells: int | None = None
    # policy stage: give System 1 an embedding of Q_vl's token positions
    # (`PolicyConfig.vl_position_embedding`); a run from a checkpoint without one adds it.
    vl_position_embedding: bool = False
    # policy stage: weight of System 1's instruction-grounding loss (`PolicyConfig.instruction_grounding`,
    # predicting the next gripper event's tool-centre-point position from the instruction and System 2's
    # image tokens); > 0 adds the grounding where the starting model has none. 0: none (the shipped recipe).
    grounding_weight: float = 0.0
    # policy stage: the grounding's learning rate is this times the run's (its attention starts from
    # nothing and has to become sharp; System 1's other weights keep the run's rate).
    grounding_lr_scale: float = 3.0
    # policy stage, with a grounding: "joint" trains all of System 1 on flow matching + W x the sub-goal
    # loss; "bind" trains only what binds the words to a place (`FlowMatchingPolicy.binding_parameters`)
    # on the sub-goal loss alone, over the approach frames, at --lr (no flow loss); "follow" keeps
    # those as its --init has them and trains the rest of System 1 (the goal projection included).
    # Inside a joint run the binding did not form; bind then follow is the two-step recipe
    # (results/instruction_grounding).
    grounding_phase: str = "joint"
    # policy stage, grounding_phase "bind" with --init: continue the --init checkpoint's grounding instead
    # of binding a fresh one, a curriculum (bind on few scenes, where the binding forms, then on more).
    keep_grounding: bool = False
    # policy stage, with a grounding: episodes of these tasks (e.g. ("stack_block",)) also train the grounding
    # on the frames that carry the held block to its release, labelled with the release position
    # (data/subgoals.py, `carry_frames`): the only frames that ask for a destination's colour
    # (results/stack_destinations). Empty: the approach frames alone.
    grounding_carry_tasks: tuple[str, ...] = ()
    # policy stage, with --init: replace the --init model's System 2 by this checkpoint's (a System 2
    # retrained by the vlm stage), keeping System 1 and System 3; the feature statistics are fitted
    # again, so not in a follow run, which keeps its bind run's (results/subcell_dense).
    system2_from: str | None = None
    # policy stage, with --init: a fresh System 1 (drawn from `seed`) on the --init model's Systems 2 and 3,
    # with its options (grounding, sub-goal offset, ...): System 1 trained from scratch on frozen
    # pretrained Systems 2 / 3, as the 10%-data arm of Table 1 is (results/data_efficiency). In a follow run
    # the fresh System 1 keeps --init's instruction grounding (`TriVLA.reset_system1(keep_binding=True)`): the
    # policy learnt anew on a grounding bound elsewhere, as a pretrained VLM brings its grounding.
    fresh_system1: bool = False
    # policy stage, with a grounding: the grounding also reads how far the gripper is closed and answers
    # with a second read-out while a block is held (`PolicyConfig.grounding_reads_gripper`), so one
    # instruction can name one block before the grasp and another after it (with --grounding-carry); a bind
    # run from a checkpoint whose grounding reads none adds it, a copy of the grounding's read-out.
    grounding_reads_gripper: bool = False
    # bind phase with grounding_reads_gripper and keep_grounding: train only the held-block read-out, so the
    # grounding's answers with no block held stay exactly --init's (and System 1's inputs with them).
    bind_held_only: bool = False
    # policy stage, with a grounding: give System 1 the grounding's sub-goal relative to the tool-centre
    # point (`PolicyConfig.subgoal_offset`); a run from a checkpoint without it adds it (starting at zero).
    subgoal_offset: bool = False
    # Checkpoints hold an exponential moving average of the trained weights with this decay (about the
    # last 1/(1 - decay) steps; train/weight_average.py); the trained weights themselves stay in the
    # training state for resuming (`export --trained-weights` writes them). 0: the last step's weights.
    ema_decay: float = 0.0
    # Write the (all-rank mean) loss to out/log.jsonl every this many steps.
    log_every: int = 10
    # Show a tqdm progress bar (rank 0 only).
    progress: bool = True
    # torch threads per process; None leaves torch's default.
    threads: int | None = None
    # "fp32", or "bf16" (autocast on CUDA; ignored on CPU where bf16 matmuls are slow).
    precision: str = "fp32"
    # Timeout of collective operations [min] (feature caching on rank 0 can take long).
    dist_timeout_minutes: float = 120.0

    # ------------------------------------------------------------------ helpers

    def resolved(self) -> "TrainConfig":
        """A copy with the stage defaults filled in and the cache folder chosen."""
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {', '.join(STAGES)}; got {self.stage!r}")
        values = {k: v for k, v in STAGE_DEFAULTS[self.stage].items() if getattr(self, k) is None}
        if self.cache_dir is None:
            values["cache_dir"] = default_cache_dir()
        return dataclasses.replace(self, **values)

    def validate(self) -> None:
        """Raises ValueError naming the field when a value is out of range (call on `resolved()`)."""
        if self.stage not in STAGES:
            raise ValueError(f"{named('stage')} must be one of {', '.join(STAGES)}; got {self.stage!r}")
        if not self.out:
            raise ValueError("out (--out) is required")
        if self.stage in ("video", "policy") and not self.data:
            raise ValueError(f"data (--data) is required for the {self.stage} stage: a LeRobot dataset folder")
        if self.extra_data and self.stage != "policy":
            raise ValueError(f"extra_data (--extra-data) applies to the policy stage only; got stage {self.stage!r}")
        for folder in self.extra_data:
            if not isinstance(folder, str) or not folder:
                raise ValueError(f"extra_data (--extra-data) must be dataset folders; got {folder!r}")
        folders = [os.path.realpath(f) for f in (self.data, *self.extra_data) if f]
        for i, folder in enumerate(folders[1:], start=1):
            if folder in folders[:i]:
                raise ValueError(f"extra_data (--extra-data) names {self.extra_data[i - 1]!r}, which is already "
                                 f"{'--data' if folders.index(folder) == 0 else 'given'}: each folder once")
        positive = ("steps", "batch_size", "checkpoint_every", "keep_checkpoints", "feature_stride",
                    "feature_batch_size", "vqa_scenes", "vqa_questions_per_scene", "log_every")
        for name in positive:
            if getattr(self, name) is None or getattr(self, name) < 1:
                raise ValueError(f"{named(name)} must be >= 1; got {getattr(self, name)}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed not in SEEDS:
            raise ValueError(f"{named('seed')} must be an integer from {SEEDS.start} to {SEEDS.stop - 1} (what torch "
                             f"and numpy seeding take); got {self.seed!r}")
        if self.lr is None or not self.lr > 0:
            raise ValueError(f"{named('lr')} must be > 0; got {self.lr}")
        if self.vqa_eval_questions < 0:
            raise ValueError(f"{named('vqa_eval_questions')} must be >= 0; got {self.vqa_eval_questions}")
        if self.workers < 0:
            raise ValueError(f"{named('workers')} must be >= 0; got {self.workers}")
        for name in ("warmup_steps", "weight_decay", "grad_clip"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{named(name)} must be >= 0; got {getattr(self, name)}")
        for name in ("beta1", "beta2"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"{named(name)} must be in [0, 1); got {getattr(self, name)}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"{named('ema_decay')} must be in [0, 1); got {self.ema_decay}")
        if not 0 <= self.min_lr_ratio <= 1:
            raise ValueError(f"{named('min_lr_ratio')} must be in [0, 1]; got {self.min_lr_ratio}")
        if self.feature_dtype not in ("float16", "bfloat16", "float32"):
            raise ValueError(f"{named('feature_dtype')} must be float16, bfloat16 or float32; got {self.feature_dtype!r}")
        if self.vl_position_embedding and self.stage != "policy":
            raise ValueError("vl_position_embedding (--vl-position-embedding) is part of System 1: set it on the "
                             f"policy stage, not the {self.stage} stage")
        if self.vl_position_embedding and not self.use_system2:
            raise ValueError("vl_position_embedding (--vl-position-embedding) embeds System 2's token positions: "
                             "it needs System 2 (drop --no-system2)")
        if not (math.isfinite(self.grounding_weight) and self.grounding_weight >= 0):
            raise ValueError(f"{named('grounding_weight')} must be a finite number >= 0; got {self.grounding_weight}")
        if not (math.isfinite(self.grounding_lr_scale) and self.grounding_lr_scale > 0):
            raise ValueError(f"{named('grounding_lr_scale')} must be a finite number > 0; got {self.grounding_lr_scale}")
        if self.grounding_weight and self.stage != "policy":
            raise ValueError("grounding_weight (--grounding-weight) weighs a loss of System 1: set it on the policy "
                             f"stage, not the {self.stage} stage")
        if self.grounding_weight and not self.use_system2:
            raise ValueError("grounding_weight (--grounding-weight) grounds the instruction in System 2's tokens: "
                             "it needs System 2 (drop --no-system2)")
        if self.grounding_phase not in GROUNDING_PHASES:
            raise ValueError(f"{named('grounding_phase')} must be one of {', '.join(GROUNDING_PHASES)}; got {self.grounding_phase!r}")
        if self.grounding_phase != "joint" and not self.grounding_weight > 0:
            raise ValueError(f"grounding_phase (--grounding-phase) {self.grounding_phase} trains with System 1's "
                             "instruction grounding: it needs grounding_weight (--grounding-weight) > 0")
        if self.grounding_carry_tasks:
            from trivla_drake.tasks.suite import TASK_NAMES

            unknown = [name for name in self.grounding_carry_tasks if name not in TASK_NAMES]
            if unknown:
                raise ValueError(f"grounding_carry_tasks (--grounding-carry) names unknown tasks {unknown}; the suite "
                                 f"has {', '.join(TASK_NAMES)}")
            if not self.grounding_weight > 0:
                raise ValueError("grounding_carry_tasks (--grounding-carry) adds frames to the grounding's loss: it "
                                 "needs grounding_weight (--grounding-weight) > 0")
        if self.keep_grounding and not (self.grounding_phase == "bind" and self.init):
            raise ValueError("keep_grounding (--keep-grounding) continues the grounding of a --init checkpoint in a "
                             "bind run: it needs --grounding-phase bind and --init")
        if self.fresh_system1 and not (self.stage == "policy" and self.init
                                       and self.grounding_phase in ("joint", "follow")):
            raise ValueError("fresh_system1 (--fresh-system1) trains a new System 1 on the Systems 2 / 3 of a --init "
                             "model: it needs --stage policy, --init and --grounding-phase joint, or follow to keep "
                             "--init's instruction grounding (bind goes on from a System 1 that has learnt something)")
        if self.system2_from is not None:
            if not (self.stage == "policy" and self.init and self.use_system2):
                raise ValueError("system2_from (--system2-from) replaces the System 2 of a --init model in the policy "
                                 "stage: it needs --stage policy, --init and System 2 (drop --no-system2)")
            if self.grounding_phase == "follow":
                raise ValueError("system2_from (--system2-from) needs its feature statistics fitted again, which a "
                                 "follow run does not do: bind (--grounding-phase bind) or train jointly first")
        if self.grounding_reads_gripper and not (self.stage == "policy" and self.grounding_weight > 0):
            raise ValueError("grounding_reads_gripper (--grounding-reads-gripper) gives System 1's instruction "
                             "grounding the gripper's closure: it needs the policy stage and grounding_weight "
                             "(--grounding-weight) > 0")
        if self.bind_held_only and not (self.grounding_phase == "bind" and self.keep_grounding
                                        and self.grounding_reads_gripper):
            raise ValueError("bind_held_only (--bind-held-only) trains only the grounding's held-block read-out: it "
                             "needs --grounding-phase bind, --keep-grounding and --grounding-reads-gripper")
        if self.subgoal_offset and not (self.stage == "policy" and self.grounding_weight > 0):
            raise ValueError("subgoal_offset (--subgoal-offset) reads System 1's instruction grounding from the tcp "
                             "position: it needs the policy stage and grounding_weight (--grounding-weight) > 0")
        if not self.dense_weight >= 0:
            raise ValueError(f"{named('dense_weight')} must be >= 0; got {self.dense_weight}")
        if self.dense_subcells is not None and self.dense_subcells < 1:
            raise ValueError(f"{named('dense_subcells')} must be >= 1; got {self.dense_subcells}")
        if self.dense_subcells is not None and not self.dense_weight:
            raise ValueError("dense_subcells (--dense-subcells) shapes the dense loss's targets: it needs "
                             "dense_weight (--dense-weight) > 0")
        if self.dense_weight and self.stage != "vlm":
            raise ValueError("dense_weight (--dense-weight) weighs a loss of the vlm stage, which trains System 2; "
                             f"not the {self.stage} stage")
        if self.precision not in ("fp32", "bf16"):
            raise ValueError(f"{named('precision')} must be fp32 or bf16; got {self.precision!r}")
        if self.future_stride is not None and self.future_stride < 1:
            raise ValueError(f"{named('future_stride')} must be >= 1; got {self.future_stride}")
        if not self.clip_seconds > 0:
            raise ValueError(f"{named('clip_seconds')} must be > 0; got {self.clip_seconds}")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"{named('threads')} must be >= 1; got {self.threads}")
        if self.stage == "video" and not self.use_system3:
            raise ValueError("the video stage trains System 3: it cannot run with --no-system3")
        if self.stage == "vlm" and not self.use_system2:
            raise ValueError("the vlm stage trains System 2: it cannot run with --no-system2")

    def __post_init__(self) -> None:
        # A saved config (JSON) gives a list: as a tuple it compares equal to the flag's on --resume.
        self.grounding_carry_tasks = tuple(self.grounding_carry_tasks)
        self.extra_data = tuple(self.extra_data or ())
        # (Anything else is left for validate() to refuse, naming the field.)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """Inverse of `to_dict`; unknown fields raise ValueError (REMOVED_FIELDS at their value are ignored)."""
        data = without_removed_fields(data, REMOVED_FIELDS, "training config")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"training config has unknown fields {sorted(unknown)}")
        return cls(**data)

    def save(self, path: str) -> None:
        """Writes the config as JSON."""
        with open(path, "w") as f:
            json.dump(self.to_dict(), f, indent=2)


def check_resume_compatible(saved: TrainConfig, current: TrainConfig) -> None:
    """Raises ValueError naming the first field that a resumed run may not change."""
    for field in dataclasses.fields(TrainConfig):
        if field.name in RESUMABLE_CHANGES:
            continue
        old, new = getattr(saved, field.name), getattr(current, field.name)
        if old != new:
            flag = flag_of(field.name)
            raise ValueError(
                f"cannot resume: {field.name}{f' ({flag})' if flag else ''} was {old!r} in the run being resumed, "
                f"now {new!r} (use the same settings, or another --out for a new run)"
            )
