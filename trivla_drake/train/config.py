"""The training configuration: one nested dataclass for the three stages, saved with every run and checkpoint as YAML.

Stages (run in this order; each starts from the previous one's checkpoint with `init`):
  video   System 3 fine-tuned on the dataset's clips with eq. (1)
  vlm     System 2 pretrained on simulator-generated visual questions (next-token loss on answers)
  policy  System 1 trained with eq. (5) (flow matching), Systems 2 and 3 frozen, their features cached

The settings every stage shares are TrainConfig's own fields; `optimizer` holds AdamW's and the schedule's; `video`,
`vlm`, `features` and `policy` hold what one stage alone reads, and a run of another stage refuses them when they
differ from their defaults. Errors name the dotted field (`policy.grounding.phase`), as `--set` writes it.

No `from __future__ import annotations` here: Drake's typed YAML loader reads the fields' types at run time.
"""

import dataclasses
import math
import os
from dataclasses import dataclass, field
from typing import Any, Optional

from trivla_drake.nn.config_dict import without_removed_fields

STAGES = ("video", "vlm", "policy")
GROUNDING_PHASES = ("joint", "bind", "follow")  # PolicyTrainConfig.grounding.phase
FEATURE_DTYPES = ("float16", "bfloat16", "float32")
PRECISIONS = ("fp32", "bf16")

# Per-stage defaults for the fields left None (chosen for the `cpu` preset on a 2-core machine;
# see the measured step times in trivla_drake/train/README.md).
STAGE_DEFAULTS: dict[str, dict[str, Any]] = {
    "video": {"batch_size": 8, "lr": 1e-4, "steps": 3000},
    "vlm": {"batch_size": 8, "lr": 3e-4, "steps": 3000},
    "policy": {"batch_size": 32, "lr": 1e-4, "steps": 10000},
}

# Seeds `train` takes: numpy's generators take no negative seed, torch.manual_seed none above 64 bits.
SEEDS = range(0, 2**64)

# Dotted fields that may differ between a run and the run it resumes (they do not change what is learned).
RESUMABLE_CHANGES = frozenset(
    {"steps", "checkpoint_every", "keep_checkpoints", "resume", "workers", "progress", "log_every", "threads",
     "cache_dir", "dist_timeout_minutes", "out", "data", "extra_data", "init", "vlm.vqa_eval_questions"}
)

# Options of experiments that left the product (their code is at git tag `research-archive`), each at the value
# every run of the product had: a saved (flat, pre-YAML) training config that lists one at that value loads (the
# field ignored); one that set it otherwise is refused, naming the field.
REMOVED_FIELDS: dict[str, Any] = {
    "fraction": 1.0, "gripper_event_weight": 1, "gripper_event_window_s": 1.0, "tcp_features": True,
    "vlm_loss_weighting": "token", "image_token_norm": False, "answer_weight": 1.0, "keep_normalization": False,
    "grounding_reads_tcp": False, "subgoal_noise": 0.0, "subgoal_yaw": False, "grounding_anchor_camera": (),
    "grounding_anchor_wrist_camera": (),
}


def default_cache_dir() -> str:
    """$XDG_CACHE_HOME/trivla_drake/train (default ~/.cache/trivla_drake/train)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "trivla_drake", "train")


@dataclass
class OptimizerConfig:
    """AdamW and the learning-rate schedule (the peak rate is TrainConfig.lr)."""

    # AdamW decoupled weight decay (matrices only).
    weight_decay: float = 0.01
    # AdamW beta1.
    beta1: float = 0.9
    # AdamW beta2.
    beta2: float = 0.95
    # Linear warm-up steps from 0 to `lr` (capped at a tenth of `steps` for short runs).
    warmup_steps: int = 100
    # After warm-up the learning rate follows a cosine from `lr` down to lr * min_lr_ratio at `steps`; 1: constant.
    min_lr_ratio: float = 0.1
    # Gradient norm clipping (0 turns it off).
    grad_clip: float = 1.0

    def validate(self, run: "TrainConfig") -> None:
        for name in ("warmup_steps", "weight_decay", "grad_clip"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"optimizer.{name} must be >= 0; got {getattr(self, name)}")
        for name in ("beta1", "beta2"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"optimizer.{name} must be in [0, 1); got {getattr(self, name)}")
        if not 0 <= self.min_lr_ratio <= 1:
            raise ValueError(f"optimizer.min_lr_ratio must be in [0, 1]; got {self.min_lr_ratio}")


@dataclass
class VideoTrainConfig:
    """The video stage's clips (System 3, eq. (1))."""

    # A clip (current frame + num_frames-1 future frames) spans about this many seconds.
    clip_seconds: float = 1.0
    # Frames between clip frames; None: round(fps * clip_seconds / (num_frames - 1)).
    future_stride: Optional[int] = None

    def validate(self, run: "TrainConfig") -> None:
        if self.future_stride is not None and self.future_stride < 1:
            raise ValueError(f"video.future_stride must be >= 1; got {self.future_stride}")
        if not self.clip_seconds > 0:
            raise ValueError(f"video.clip_seconds must be > 0; got {self.clip_seconds}")


@dataclass
class VlmTrainConfig:
    """The vlm stage's generated visual questions and System 2's dense loss."""

    # Simulator scenes rendered for the visual-question set.
    vqa_scenes: int = 500
    # Questions asked about each scene.
    vqa_questions_per_scene: int = 8
    # Held-out questions scored at the end of the run (multiple-choice accuracy); 0 skips it.
    vqa_eval_questions: int = 400
    # Seed of the scene sampling and question choice (part of the VQA set's key).
    vqa_seed: int = 0
    # Weight of the dense loss of System 2's block head (which blocks each image token's cell shows, from the
    # renderer's label images; `VisionLanguageConfig.dense_classes`); a run from a checkpoint without the head adds
    # one. 0: no dense loss.
    dense_weight: float = 0.0
    # With dense_weight: sub-cells per side of each token's cell the block head tells apart
    # (`VisionLanguageConfig.dense_subcells`); a starting head with others is replaced by a fresh one.
    # None: as the init model has them (1 for a fresh model or one without a head).
    dense_subcells: Optional[int] = None

    def validate(self, run: "TrainConfig") -> None:
        for name in ("vqa_scenes", "vqa_questions_per_scene"):
            _check_positive(self, name, "vlm.")
        if self.vqa_eval_questions < 0:
            raise ValueError(f"vlm.vqa_eval_questions must be >= 0; got {self.vqa_eval_questions}")
        if not self.dense_weight >= 0:
            raise ValueError(f"vlm.dense_weight must be >= 0; got {self.dense_weight}")
        if self.dense_subcells is not None and self.dense_subcells < 1:
            raise ValueError(f"vlm.dense_subcells must be >= 1; got {self.dense_subcells}")
        if self.dense_subcells is not None and not self.dense_weight:
            raise ValueError("vlm.dense_subcells shapes the dense loss's targets: it needs vlm.dense_weight > 0")


@dataclass
class FeaturesConfig:
    """The policy stage's cache of System 2/3 features (computed once, part of the cache key)."""

    # Cache (and train on) every this-many-th frame of each episode.
    stride: int = 1
    # dtype of the cached features ("float16" halves the disk; "float32" is exact).
    dtype: str = "float16"
    # Frames per batch when computing the cached features.
    batch_size: int = 16
    # Seed of System 3's noise latents for the cached features.
    seed: int = 0

    def validate(self, run: "TrainConfig") -> None:
        for name in ("stride", "batch_size"):
            _check_positive(self, name, "features.")
        if self.dtype not in FEATURE_DTYPES:
            raise ValueError(f"features.dtype must be one of {', '.join(FEATURE_DTYPES)}; got {self.dtype!r}")


@dataclass
class GroundingTrainConfig:
    """System 1's instruction grounding (`PolicyConfig.instruction_grounding`): the instruction's tokens query System
    2's image tokens for the next gripper event's tool-centre-point position, trained with a sub-goal loss."""

    # Weight of the grounding's sub-goal loss; > 0 adds the grounding where the starting model has none. 0: none.
    weight: float = 0.0
    # The grounding's learning rate is this times the run's in a joint run (its attention starts from nothing and
    # has to become sharp; System 1's other weights keep the run's rate).
    lr_scale: float = 3.0
    # "joint" trains all of System 1 on flow matching + weight x the sub-goal loss; "bind" trains only what binds
    # the words to a place (`FlowMatchingPolicy.binding_parameters`) on the sub-goal loss alone, over the approach
    # frames (no flow loss); "follow" keeps those as its init has them and trains the rest of System 1. Inside a
    # joint run the binding did not form; bind then follow is the two-step recipe.
    phase: str = "joint"
    # phase "bind" with init: continue the init checkpoint's grounding instead of binding a fresh one, a curriculum
    # (bind on few scenes, where the binding forms, then on more).
    keep: bool = False
    # Episodes of these tasks (e.g. [stack_block]) also train the grounding on the frames that carry the held block
    # to its release, labelled with the release position (data/subgoals.py, `carry_frames`). Empty: the approach
    # frames alone.
    carry_tasks: list[str] = field(default_factory=list)
    # The grounding also reads how far the gripper is closed and answers with a second read-out while a block is
    # held (`PolicyConfig.grounding_reads_gripper`), so one instruction can name one block before the grasp and
    # another after it; a bind run from a checkpoint whose grounding reads none adds it, a copy of the read-out.
    reads_gripper: bool = False
    # bind phase with reads_gripper and keep: train only the held-block read-out, so the grounding's answers with
    # no block held stay exactly init's (and System 1's inputs with them).
    bind_held_only: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.carry_tasks, tuple):
            self.carry_tasks = list(self.carry_tasks)

    def validate(self, run: "TrainConfig") -> None:
        if not (math.isfinite(self.weight) and self.weight >= 0):
            raise ValueError(f"policy.grounding.weight must be a finite number >= 0; got {self.weight}")
        if not (math.isfinite(self.lr_scale) and self.lr_scale > 0):
            raise ValueError(f"policy.grounding.lr_scale must be a finite number > 0; got {self.lr_scale}")
        if self.weight and not run.use_system2:
            raise ValueError("policy.grounding.weight grounds the instruction in System 2's tokens: it needs System 2 "
                             "(use_system2 true)")
        if self.phase not in GROUNDING_PHASES:
            raise ValueError(f"policy.grounding.phase must be one of {', '.join(GROUNDING_PHASES)}; got {self.phase!r}")
        needs_weight = [name for name, on in (("phase", self.phase != "joint"), ("carry_tasks", self.carry_tasks),
                                              ("reads_gripper", self.reads_gripper)) if on]
        if needs_weight and not self.weight > 0:
            raise ValueError(f"policy.grounding.{needs_weight[0]} works on System 1's instruction grounding: it needs "
                             "policy.grounding.weight > 0")
        if self.carry_tasks:
            from trivla_drake.tasks.suite import TASK_NAMES

            unknown = [name for name in self.carry_tasks if name not in TASK_NAMES]
            if unknown:
                raise ValueError(f"policy.grounding.carry_tasks names unknown tasks {unknown}; the suite has "
                                 f"{', '.join(TASK_NAMES)}")
        if self.keep and not (self.phase == "bind" and run.init):
            raise ValueError("policy.grounding.keep continues the grounding of an init checkpoint in a bind run: it "
                             "needs policy.grounding.phase bind and init")
        if self.bind_held_only and not (self.phase == "bind" and self.keep and self.reads_gripper):
            raise ValueError("policy.grounding.bind_held_only trains only the grounding's held-block read-out: it "
                             "needs policy.grounding.phase bind, policy.grounding.keep and policy.grounding.reads_gripper")


@dataclass
class PolicyTrainConfig:
    """The policy stage's options of System 1 (each added to an init model that lacks it)."""

    # Give System 1 an embedding of Q_vl's token positions (`PolicyConfig.vl_position_embedding`).
    vl_position_embedding: bool = False
    # With init: a fresh System 1 (drawn from `seed`) on the init model's Systems 2 and 3, keeping its System 1
    # options; in a follow run it keeps init's instruction grounding (`TriVLA.reset_system1(keep_binding=True)`).
    fresh_system1: bool = False
    # With init: replace the init model's System 2 by this checkpoint's (a System 2 retrained by the vlm stage),
    # keeping System 1 and System 3; the feature statistics are fitted again, so not in a follow run.
    system2_from: Optional[str] = None
    # With a grounding: give System 1 the grounding's sub-goal relative to the tool-centre point
    # (`PolicyConfig.subgoal_offset`); a run from a checkpoint without it adds it (starting at zero).
    subgoal_offset: bool = False
    # System 1's instruction grounding.
    grounding: GroundingTrainConfig = field(default_factory=GroundingTrainConfig)

    def validate(self, run: "TrainConfig") -> None:
        if self.vl_position_embedding and not run.use_system2:
            raise ValueError("policy.vl_position_embedding embeds System 2's token positions: it needs System 2 "
                             "(use_system2 true)")
        self.grounding.validate(run)
        if self.fresh_system1 and not (run.init and self.grounding.phase in ("joint", "follow")):
            raise ValueError("policy.fresh_system1 trains a new System 1 on the Systems 2 / 3 of an init model: it "
                             "needs init and policy.grounding.phase joint, or follow to keep init's instruction "
                             "grounding (bind goes on from a System 1 that has learnt something)")
        if self.system2_from is not None:
            if not (run.init and run.use_system2):
                raise ValueError("policy.system2_from replaces the System 2 of an init model: it needs init and "
                                 "System 2 (use_system2 true)")
            if self.grounding.phase == "follow":
                raise ValueError("policy.system2_from needs its feature statistics fitted again, which a follow run "
                                 "does not do: bind (policy.grounding.phase bind) or train jointly first")
        if self.subgoal_offset and not self.grounding.weight > 0:
            raise ValueError("policy.subgoal_offset reads System 1's instruction grounding from the tcp position: it "
                             "needs policy.grounding.weight > 0")


# The sub-configs a single stage reads: set away from their defaults in a run of another stage, they are refused.
STAGE_SECTIONS = {"video": "video", "vlm": "vlm", "features": "policy", "policy": "policy"}


@dataclass
class TrainConfig:
    """Everything a training run depends on. Fields left None get their stage's default in `resolved()`."""

    # Which system to train: "video" (System 3), "vlm" (System 2) or "policy" (System 1).
    stage: str = ""
    # Output folder: checkpoints/step-XXXXXXXX/ (periodic), final/ (the last), log.jsonl, summary.json,
    # train_config.yaml.
    out: str = ""
    # LeRobot dataset folder (video and policy stages). For the vlm stage: an optional folder for the
    # generated visual-question set (default: a folder in `cache_dir` named by the generation settings).
    data: Optional[str] = None
    # Policy stage: more LeRobot dataset folders trained on together with `data` (same state, action and
    # cameras; normalisation over all; an episode that two folders both hold is trained on once).
    extra_data: list[str] = field(default_factory=list)
    # Model preset (tiny, cpu, paper) of a fresh model; None: the init checkpoint's preset, else "cpu".
    # Given together with `init`, it must match the checkpoint's preset.
    preset: Optional[str] = None
    # Checkpoint folder to start from (the previous stage's final/); None: a fresh `preset` model.
    init: Optional[str] = None
    # Optimizer steps in all (a resumed run continues up to this count). None: the stage's default.
    steps: Optional[int] = None
    # Samples per process per step (the effective batch is batch_size x world size). None: stage default.
    batch_size: Optional[int] = None
    # Peak learning rate of AdamW. None: the stage's default.
    lr: Optional[float] = None
    # Seed of everything random: fresh-model initialisation, data order, diffusion/flow noise.
    seed: int = 0
    # Continue from the newest checkpoint in `out` (model, optimizer, step, data position, RNG states).
    resume: bool = False
    # Keep System 2 (vision-language tokens) in the model (every stage builds the model); False is the Table 4
    # ablation "1+3".
    use_system2: bool = True
    # Keep System 3 (dynamics features) in the model; False is the Table 4 ablation "1+2".
    use_system3: bool = True
    # Dataset camera of System 2/3's static (third-person) view (video and policy stages).
    static_camera: str = "observation.images.static"
    # Dataset camera of the wrist view.
    wrist_camera: str = "observation.images.wrist"
    # Checkpoints hold an exponential moving average of the trained weights with this decay (about the
    # last 1/(1 - decay) steps; train/weight_average.py); the trained weights themselves stay in the
    # training state for resuming. 0: the last step's weights.
    ema_decay: float = 0.0
    # Write a checkpoint every this many steps (and always at the last step).
    checkpoint_every: int = 500
    # Periodic checkpoints kept on disk (older ones are deleted once a newer one is complete).
    keep_checkpoints: int = 2
    # DataLoader worker processes per training process (0 loads in the training process).
    workers: int = 0
    # Folder for data made once and reused: decoded clips, the VQA set, cached System 2/3 features.
    # Entries are named by hashes of everything they depend on, so runs can share it. None: default_cache_dir().
    cache_dir: Optional[str] = None
    # Write the (all-rank mean) loss to out/log.jsonl every this many steps.
    log_every: int = 10
    # Show a tqdm progress bar (rank 0 only).
    progress: bool = True
    # torch threads per process; None leaves torch's default.
    threads: Optional[int] = None
    # "fp32", or "bf16" (autocast on CUDA; ignored on CPU where bf16 matmuls are slow).
    precision: str = "fp32"
    # Timeout of collective operations [min] (feature caching on rank 0 can take long).
    dist_timeout_minutes: float = 120.0
    # AdamW and the learning-rate schedule.
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    # Video stage: its clips.
    video: VideoTrainConfig = field(default_factory=VideoTrainConfig)
    # vlm stage: its visual questions and dense loss.
    vlm: VlmTrainConfig = field(default_factory=VlmTrainConfig)
    # Policy stage: the cached System 2/3 features.
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    # Policy stage: System 1's options.
    policy: PolicyTrainConfig = field(default_factory=PolicyTrainConfig)

    def __post_init__(self) -> None:
        # A caller's tuple of folders reads as the list a saved config (YAML) gives: they compare equal on resume.
        if isinstance(self.extra_data, tuple):
            self.extra_data = list(self.extra_data)

    def resolved(self) -> "TrainConfig":
        """A copy with the stage defaults filled in and the cache folder chosen."""
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {', '.join(STAGES)}; got {self.stage!r}")
        values = {k: v for k, v in STAGE_DEFAULTS[self.stage].items() if getattr(self, k) is None}
        if self.cache_dir is None:
            values["cache_dir"] = default_cache_dir()
        return dataclasses.replace(self, **values)

    def validate(self) -> None:
        """Raises ValueError naming the dotted field when a value is out of range (call on `resolved()`)."""
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {', '.join(STAGES)}; got {self.stage!r}")
        if not self.out:
            raise ValueError("out is required: the run's folder")
        if self.stage in ("video", "policy") and not self.data:
            raise ValueError(f"data is required for the {self.stage} stage: a LeRobot dataset folder")
        self._check_stage_sections()
        self._check_data_folders()
        for name in ("steps", "batch_size", "checkpoint_every", "keep_checkpoints", "log_every"):
            _check_positive(self, name, "")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed not in SEEDS:
            raise ValueError(f"seed must be an integer from {SEEDS.start} to {SEEDS.stop - 1} (what torch and numpy "
                             f"seeding take); got {self.seed!r}")
        if self.lr is None or not self.lr > 0:
            raise ValueError(f"lr must be > 0; got {self.lr}")
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0; got {self.workers}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1); got {self.ema_decay}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}; got {self.precision!r}")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be >= 1; got {self.threads}")
        if self.stage == "video" and not self.use_system3:
            raise ValueError("the video stage trains System 3: it cannot run with use_system3 false")
        if self.stage == "vlm" and not self.use_system2:
            raise ValueError("the vlm stage trains System 2: it cannot run with use_system2 false")
        for section in ("optimizer", *STAGE_SECTIONS):
            if STAGE_SECTIONS.get(section, self.stage) == self.stage:
                getattr(self, section).validate(self)

    def _check_stage_sections(self) -> None:
        """A stage's own settings set in a run of another stage: refused, naming the field and the stage."""
        for section, stage in STAGE_SECTIONS.items():
            if stage == self.stage:
                continue
            changed = differing_fields(getattr(self, section), type(getattr(self, section))(), prefix=f"{section}.")
            if changed:
                dotted, value, _ = changed[0]
                raise ValueError(f"{dotted} ({value!r}) is a setting of the {stage} stage; this run is the "
                                 f"{self.stage} stage: leave it at its default")
        if self.extra_data and self.stage != "policy":
            raise ValueError(f"extra_data applies to the policy stage only; got stage {self.stage!r}")

    def _check_data_folders(self) -> None:
        for folder in self.extra_data:
            if not isinstance(folder, str) or not folder:
                raise ValueError(f"extra_data must be dataset folders; got {folder!r}")
        folders = [os.path.realpath(f) for f in (self.data, *self.extra_data) if f]
        for i, folder in enumerate(folders[1:], start=1):
            if folder in folders[:i]:
                raise ValueError(f"extra_data names {self.extra_data[i - 1]!r}, which is already "
                                 f"{'data' if folders.index(folder) == 0 else 'given'}: each folder once")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """The config of its nested mapping (`dataclasses.asdict`: what train_config.yaml holds), also reading a flat
        training config of before the nested one (train_config.json: its fields mapped by FLAT_FIELD_PATHS;
        REMOVED_FIELDS at their value ignored); ValueError naming an unknown field."""
        if not any(isinstance(value, dict) for value in data.values()) and set(data) & set(FLAT_FIELD_PATHS):
            data = nested_from_flat(without_removed_fields(data, REMOVED_FIELDS, "training config"))
        return config_from_mapping(cls, data)


# Where each field of the flat TrainConfig of before (train_config.json) lives now; the rest kept their names.
FLAT_FIELD_PATHS = {
    **{name: f"optimizer.{name}" for name in ("weight_decay", "beta1", "beta2", "warmup_steps", "min_lr_ratio",
                                              "grad_clip")},
    "clip_seconds": "video.clip_seconds", "future_stride": "video.future_stride",
    **{name: f"vlm.{name}" for name in ("vqa_scenes", "vqa_questions_per_scene", "vqa_eval_questions", "vqa_seed",
                                        "dense_weight", "dense_subcells")},
    "feature_stride": "features.stride", "feature_dtype": "features.dtype", "feature_batch_size": "features.batch_size",
    "feature_seed": "features.seed",
    **{name: f"policy.{name}" for name in ("vl_position_embedding", "fresh_system1", "system2_from",
                                           "subgoal_offset")},
    "grounding_weight": "policy.grounding.weight", "grounding_lr_scale": "policy.grounding.lr_scale",
    "grounding_phase": "policy.grounding.phase", "keep_grounding": "policy.grounding.keep",
    "grounding_carry_tasks": "policy.grounding.carry_tasks", "grounding_reads_gripper": "policy.grounding.reads_gripper",
    "bind_held_only": "policy.grounding.bind_held_only",
}


def nested_from_flat(flat: dict[str, Any]) -> dict[str, Any]:
    """The nested mapping of a flat training config's fields (old names, FLAT_FIELD_PATHS)."""
    nested: dict[str, Any] = {}
    for name, value in flat.items():
        *parents, last = FLAT_FIELD_PATHS.get(name, name).split(".")
        target = nested
        for parent in parents:
            target = target.setdefault(parent, {})
        target[last] = list(value) if isinstance(value, tuple) else value
    return nested


def differing_fields(config, reference, *, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted field, value in `config`, value in `reference`) of every leaf field where two configs of one
    dataclass differ, in field order."""
    found = []
    for f in dataclasses.fields(config):
        mine, theirs = getattr(config, f.name), getattr(reference, f.name)
        if dataclasses.is_dataclass(mine):
            found += differing_fields(mine, theirs, prefix=f"{prefix}{f.name}.")
        elif mine != theirs:
            found.append((f"{prefix}{f.name}", mine, theirs))
    return found


def check_resume_compatible(saved: TrainConfig, current: TrainConfig) -> None:
    """Raises ValueError naming the first dotted field that a resumed run may not change."""
    for dotted, old, new in differing_fields(saved, current):
        if dotted not in RESUMABLE_CHANGES:
            raise ValueError(f"cannot resume: {dotted} was {old!r} in the run being resumed, now {new!r} (use the "
                             "same settings, or another out for a new run)")


def _check_positive(config, name: str, prefix: str) -> None:
    value = getattr(config, name)
    if value is None or value < 1:
        raise ValueError(f"{prefix}{name} must be >= 1; got {value}")


def config_from_mapping(cls, data: dict[str, Any], *, prefix: str = ""):
    """An instance of the (nested) config dataclass `cls` from a mapping that we wrote (a saved config's plain YAML or
    JSON; Drake is not needed to read it back); ValueError naming an unknown field. Untyped: a user's file goes
    through config_io.load_config instead."""
    if not isinstance(data, dict):
        raise ValueError(f"config: {prefix.rstrip('.') or '(top)'} must be a mapping; got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(f"{prefix}{name}" for name in set(data) - set(fields))
    if unknown:
        raise ValueError(f"{cls.__name__} has no fields {unknown}")
    values = {}
    for name, value in data.items():
        default = fields[name].default_factory() if fields[name].default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(default):
            value = config_from_mapping(type(default), value, prefix=f"{prefix}{name}.")
        elif isinstance(value, tuple):
            value = list(value)
        values[name] = value
    return cls(**values)
