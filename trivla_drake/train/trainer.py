"""`train(config)`: one training stage (video, vlm or policy), in one process or under torchrun.

    from trivla_drake.train import TrainConfig, train
    summary = train(TrainConfig(stage="policy", data="data/demos", out="runs/policy", init="runs/vlm/final"))

What happens, in order: the output folder is checked (an existing run needs `resume`); the model is
built (resumed checkpoint > `init` checkpoint > fresh preset) and checked against the dataset before
anything is computed; the stage's data is prepared once and cached (decoded clips, the generated VQA
set, System 2/3 features); then AdamW steps with warm-up + cosine learning rate, a checkpoint every
`checkpoint_every` steps and at the end (OUT/final, loadable by `trivla_drake.nn.load_checkpoint`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import random
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from trivla_drake.data.durable import atomic_write_text
from trivla_drake.nn.checkpoint import load_checkpoint, read_checkpoint_config
from trivla_drake.nn.config import PRESETS, TriVLAConfig, make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train import checkpoints as ckpt
from trivla_drake.train.config import TrainConfig, check_resume_compatible
from trivla_drake.train.distributed import DistEnv, setup_distributed, teardown_distributed
from trivla_drake.train.features import hash_module_weights
from trivla_drake.train.weight_average import WeightAverage

# System 1's state MLP reads the tool-centre-point pose computed from the joint angles (policy.tcp_features):
# every run adds it where its start has none (the switch to leave it out went with the experiments).
TCP_FEATURES = True

StepCallback = Callable[[int], None]


# ---------------------------------------------------------------------------------------------
# Model


def _transfer_weights(source: nn.Module, target: nn.Module) -> int:
    """Copies every tensor of `source` whose name and shape exist in `target`; returns how many."""
    src = source.state_dict()
    dst = target.state_dict()
    matched = {k: v for k, v in src.items() if k in dst and dst[k].shape == v.shape}
    target.load_state_dict(matched, strict=False)
    return len(matched)


def apply_ablations(
    model: TriVLA, use_system2: bool, use_system3: bool, where: str, tcp_features: bool | None = None,
    vl_position_embedding: bool = False,
    dense_classes: int = 0,
    instruction_grounding: bool = False,
    subgoal_offset: bool = False,
    dense_subcells: int | None = None,
    grounding_reads_gripper: bool = False,
) -> TriVLA:
    """`model` with Systems 2 / 3 dropped as asked, System 1's tcp features set to `tcp_features`
    (None: as they are), rebuilt when anything changes (keeping every weight that still fits), with:
    - `vl_position_embedding`: a fresh embedding of Q_vl's token positions in System 1 where it has none;
    - `dense_classes` > 0: a fresh block head on System 2's image tokens where it has none, or where its
      `dense_subcells` differ from those asked (None: as they are);
    - `instruction_grounding`: a fresh instruction grounding in System 1 where it has none;
    - `subgoal_offset`: a fresh sub-goal offset encoder (output at zero) where it has none;
    - `grounding_reads_gripper`: a grounding with a held-block read-out (a copy of its read-out) where it
      has none.
    A system missing from `model` cannot be switched back on: ValueError."""
    cfg = model.config
    for name, wanted, have in (("System 2", use_system2, cfg.use_system2), ("System 3", use_system3, cfg.use_system3)):
        if wanted and not have:
            raise ValueError(
                f"{where} has no {name} (it was trained without it); it cannot be switched back on: "
                f"pass --no-system{name[-1]} or start from a checkpoint that has it"
            )
    tcp = cfg.policy.tcp_features if tcp_features is None else tcp_features
    vl_position = use_system2 and (cfg.policy.vl_position_embedding or vl_position_embedding)
    classes = cfg.vision_language.dense_classes or (dense_classes if use_system2 else 0)
    subcells = cfg.vision_language.dense_subcells if dense_subcells is None or not classes else dense_subcells
    grounding = use_system2 and (cfg.policy.instruction_grounding or instruction_grounding)
    offset = grounding and tcp and (cfg.policy.subgoal_offset or subgoal_offset)
    reads_gripper = grounding and (cfg.policy.grounding_reads_gripper or grounding_reads_gripper)
    if (cfg.use_system2, cfg.use_system3, cfg.policy.tcp_features, cfg.policy.vl_position_embedding,
            cfg.vision_language.dense_classes, cfg.policy.instruction_grounding, cfg.policy.subgoal_offset,
            cfg.vision_language.dense_subcells, cfg.policy.grounding_reads_gripper) == (
            use_system2, use_system3, tcp, vl_position, classes, grounding, offset, subcells, reads_gripper):
        return model
    new_config = dataclasses.replace(
        cfg, use_system2=use_system2, use_system3=use_system3,
        policy=dataclasses.replace(cfg.policy, tcp_features=tcp, vl_position_embedding=vl_position,
                                   instruction_grounding=grounding, subgoal_offset=offset,
                                   grounding_reads_gripper=reads_gripper),
        vision_language=dataclasses.replace(cfg.vision_language, dense_classes=classes, dense_subcells=subcells),
    )
    tokenizers = {}
    if use_system2:
        tokenizers["vision_language"] = model.vision_language.tokenizer
    if use_system3:
        tokenizers["dynamics"] = model.dynamics.tokenizer
    components = {k: v for k, v in model.component_configs().items()
                  if (k == "vision_language" and use_system2) or (k == "dynamics" and use_system3)}
    new = TriVLA(new_config, normalization=model.normalization, component_configs=components,
                 tokenizers=tokenizers, load_pretrained=False)
    _transfer_weights(model, new)
    if reads_gripper and not cfg.policy.grounding_reads_gripper:
        new.policy.grounding.start_held_from_open()
    return new


def replace_system2(model: TriVLA, donor: TriVLA, where: str) -> TriVLA:
    """`model` with its System 2 replaced by `donor`'s (trimmed above its read-out layer when
    `model`'s is), in place. The donor must give Q_vl of the same width and layout (prompt head and
    image tokens), which System 1 reads; ValueError naming what differs otherwise."""
    mine, theirs = model.vision_language, donor.vision_language
    if mine is None or theirs is None:
        raise ValueError(f"{where}: replacing System 2 needs one in both models "
                         f"(--init has {'none' if mine is None else 'one'}, the donor {'none' if theirs is None else 'one'})")
    for name, a, b in (("Q_vl width (hidden size)", mine.hidden_size, theirs.hidden_size),
                       ("image size", mine.image_size, theirs.image_size),
                       ("image tokens per view", mine.num_image_tokens, theirs.num_image_tokens),
                       ("prompt head + image tokens", mine.instruction_offset(2), theirs.instruction_offset(2))):
        if a != b:
            raise ValueError(f"{where}: its System 2's {name} is {b}, the --init model's {a}: "
                             "System 1 reads Q_vl laid out as the --init model's")
    if mine.config.drop_unused_llm_layers:
        theirs.drop_layers_above_readout()
    model.vision_language = theirs.to(model.device)
    model.config = dataclasses.replace(model.config, vision_language=theirs.config)
    return model


def _resolve_preset(config: TrainConfig) -> str:
    if config.system2_from is not None and not Path(config.system2_from).is_dir():
        raise FileNotFoundError(f"--system2-from {config.system2_from!r} is not a checkpoint directory")
    if config.init:
        if not Path(config.init).is_dir():
            raise FileNotFoundError(f"--init {config.init!r} is not a checkpoint directory")
        meta = read_checkpoint_config(config.init)
        init_preset = meta.get("preset")
        if config.preset is not None and config.preset != init_preset:
            raise ValueError(
                f"--init checkpoint {config.init!r} is preset {init_preset!r} but --preset is {config.preset!r} "
                "(another preset): drop --preset or start from a checkpoint of that preset"
            )
        return init_preset
    preset = config.preset or "cpu"
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid presets: {', '.join(sorted(PRESETS))}")
    return preset


def _dense_classes(config: TrainConfig) -> int:
    """Classes of System 2's block head a run asks for: one per block colour with a dense loss."""
    from trivla_drake.tasks.scene import BLOCK_COLORS

    return len(BLOCK_COLORS) if config.dense_weight > 0 else 0


def fresh_model_config(config: TrainConfig) -> TriVLAConfig:
    """The `preset` model a run without --init or resume builds, with the run's options. A vlm run
    keeps every LLM layer (a preset may build only those up to the read-out, as `paper` does):
    its answers are read from the LLM's last layer, not from Q_vl."""
    cfg = make_config(config.preset, init_seed=config.seed,
                      use_system2=config.use_system2, use_system3=config.use_system3)
    vision_language = cfg.vision_language
    return dataclasses.replace(
        cfg, policy=dataclasses.replace(cfg.policy, tcp_features=TCP_FEATURES,
                                        vl_position_embedding=config.vl_position_embedding and config.use_system2,
                                        instruction_grounding=config.grounding_weight > 0,
                                        subgoal_offset=config.subgoal_offset,
                                        grounding_reads_gripper=config.grounding_reads_gripper),
        vision_language=dataclasses.replace(
            vision_language, dense_classes=_dense_classes(config) if config.use_system2 else 0,
            dense_subcells=config.dense_subcells or 1,
            drop_unused_llm_layers=vision_language.drop_unused_llm_layers and config.stage != "vlm"),
    )


def build_model(config: TrainConfig, resume_from: Path | None) -> TriVLA:
    """The model a run starts from: the resumed checkpoint, the `init` checkpoint (with ablations
    applied), or a fresh `preset` model initialised from `seed`."""
    if resume_from is not None:
        model = load_checkpoint(str(resume_from))
        where = f"checkpoint {resume_from}"
    elif config.init:
        model = load_checkpoint(config.init)
        where = f"--init checkpoint {config.init}"
        if config.grounding_phase == "follow" and model.policy.grounding is None:
            raise ValueError(f"grounding_phase (--grounding-phase) follow keeps the instruction grounding of its "
                             f"{where}, which has none: train one with --grounding-phase bind first")
        if (config.grounding_phase == "follow" and config.grounding_reads_gripper
                and not model.config.policy.grounding_reads_gripper):
            raise ValueError(f"grounding_reads_gripper (--grounding-reads-gripper) changes the instruction grounding, "
                             f"which a follow run keeps as its {where} has it (reading no gripper): bind one with "
                             f"--grounding-reads-gripper first")
        if config.keep_grounding and model.policy.grounding is None:
            raise ValueError(f"keep_grounding (--keep-grounding) continues the instruction grounding of its {where}, "
                             f"which has none: bind one without --keep-grounding first")
        model = apply_ablations(model, config.use_system2, config.use_system3, where, TCP_FEATURES,
                                config.vl_position_embedding, _dense_classes(config), config.grounding_weight > 0,
                                config.subgoal_offset, config.dense_subcells if config.dense_weight > 0 else None,
                                config.grounding_reads_gripper)
        if config.system2_from is not None:
            model = replace_system2(model, load_checkpoint(config.system2_from), f"--system2-from {config.system2_from}")
        if config.fresh_system1:
            model.reset_system1(config.seed, keep_binding=config.grounding_phase == "follow")
        if config.grounding_phase == "bind" and not config.keep_grounding:
            # A bind run learns the binding from a fresh grounding (a resumed one keeps its own): one
            # from a joint run stayed at chance when bound further, a fresh one bound
            # (results/instruction_grounding).
            torch.manual_seed(config.seed)
            model.policy.reset_grounding()
    else:
        if config.grounding_phase == "follow":
            raise ValueError("grounding_phase (--grounding-phase) follow keeps the instruction grounding of its "
                             "--init checkpoint: pass --init with a --grounding-phase bind run's checkpoint")
        return TriVLA(fresh_model_config(config))
    if model.config.preset != config.preset:
        raise ValueError(f"{where} is preset {model.config.preset!r}, not {config.preset!r}")
    if (model.config.use_system2, model.config.use_system3) != (config.use_system2, config.use_system3):
        raise ValueError(f"{where} has use_system2/3 = {model.config.use_system2}/{model.config.use_system3}, "
                         f"the run asks {config.use_system2}/{config.use_system3}")
    vl_config = model.config.vision_language
    if config.stage == "vlm" and model.vision_language is not None and vl_config.drop_unused_llm_layers:
        raise ValueError(f"{where} has vision_language.drop_unused_llm_layers: its LLM ends at the read-out "
                         f"layer (select_layer {vl_config.select_layer}), so the vlm stage would train the "
                         f"answers on Q_vl itself; start from the checkpoint it was exported from "
                         f"(export without --drop-unused-llm-layers)")
    if model.config.policy.tcp_features != TCP_FEATURES:
        raise ValueError(f"{where} has policy.tcp_features = {model.config.policy.tcp_features}: every run of this "
                         f"code trains with the tcp features")
    return model


def check_grounding(reader, grounding_weight: float, where: str) -> None:
    """A System 1 with instruction grounding trains its sub-goal loss: it needs a positive
    `grounding_weight` and the dataset's tool-centre-point poses (the labels, data/subgoals.py)."""
    from trivla_drake.data.samples import TCP_POSE_KEY

    if not grounding_weight > 0:
        raise ValueError(f"{where} has System 1's instruction grounding: its sub-goal loss needs "
                         f"grounding_weight (--grounding-weight) > 0; got {grounding_weight}")
    if TCP_POSE_KEY not in reader.features:
        raise ValueError(f"grounding_weight (--grounding-weight) trains on sub-goals from {TCP_POSE_KEY!r}, "
                         f"which dataset {reader.root} does not have")


def check_resumed_normalization(saved, fitted, where: str) -> None:
    """A resumed policy run keeps training on the data it started on: ValueError naming --data / --extra-data
    when the statistics those folders give now differ from the checkpoint's (other or more folders)."""
    saved_dict, fitted_dict = saved.to_dict(), fitted.to_dict()
    differing = [k for k in saved_dict if not np.allclose(saved_dict[k], fitted_dict[k], rtol=1e-5, atol=1e-7)]
    if differing:
        raise ValueError(f"data (--data) / extra_data (--extra-data) give other statistics ({', '.join(differing)}) "
                         f"than {where} was trained on: resume on the same folders (or start a new run with --init)")


def trainable_module(model: TriVLA, stage: str) -> nn.Module:
    """What a stage trains: System 3's UNet and text projection (its VAE and CLIP stay frozen, as in
    VPP), all of System 2, or System 1."""
    if stage == "video":
        return nn.ModuleList([model.dynamics.unet, model.dynamics.text_projection])
    if stage == "vlm":
        return model.vision_language
    return model.policy


class StageLoss(nn.Module):
    """The stage's loss as a module's forward (what DistributedDataParallel wraps)."""

    def __init__(self, model: TriVLA, stage: str, generator: torch.Generator, dense_weight: float = 0.0,
                 grounding_weight: float = 0.0, grounding_phase: str = "joint") -> None:
        super().__init__()
        self.model, self.stage, self.generator = model, stage, generator
        self.dense_weight = dense_weight
        self.grounding_weight, self.grounding_phase = grounding_weight, grounding_phase

    def forward(self, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, float]]:
        if self.stage == "video":
            return self.model.compute_video_loss(batch, generator=self.generator)
        if self.stage == "vlm":
            return self.model.compute_vlm_loss(batch, dense_weight=self.dense_weight)
        if self.grounding_phase == "bind":
            return self.model.compute_grounding_loss(batch)
        return self.model.compute_loss(batch, generator=self.generator, grounding_weight=self.grounding_weight)


# ---------------------------------------------------------------------------------------------
# Random states


def _rank_seed(seed: int, rank: int) -> int:
    return int(hashlib.sha256(f"noise:{seed}:{rank}".encode()).hexdigest()[:15], 16)


def _rng_state(generator: torch.Generator) -> dict[str, Any]:
    np_state = np.random.get_state()
    return {
        "noise": generator.get_state(),
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": [np_state[0], np_state[1].tolist(), int(np_state[2]), int(np_state[3]), float(np_state[4])],
        "python": random.getstate(),
    }


def _set_rng_state(state: dict[str, Any], generator: torch.Generator) -> None:
    generator.set_state(state["noise"])
    torch.set_rng_state(state["torch"])
    if torch.cuda.is_available() and state.get("cuda"):
        torch.cuda.set_rng_state_all(state["cuda"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    random.setstate(_as_tuples(state["python"]))


def _as_tuples(value: Any) -> Any:
    return tuple(_as_tuples(v) for v in value) if isinstance(value, (list, tuple)) else value


def weights_digest(model: nn.Module) -> str:
    """sha256 of every weight and buffer of `model` (equal digests = bit-identical weights)."""
    hasher = hashlib.sha256()
    hash_module_weights(model, hasher)
    return hasher.hexdigest()


def _note(env: DistEnv, message: str) -> None:
    """A one-line notice on stderr, from rank 0 only."""
    if env.is_main:
        print(f"trivla-drake train: note: {message}", file=sys.stderr)


def _truncate_log(path: Path, last_step: int) -> None:
    """Keeps the log lines of steps <= last_step (all of them gone for a fresh run)."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line)["step"] <= last_step:
                kept.append(line)
        except (ValueError, KeyError, TypeError):
            continue
    atomic_write_text(path, "".join(line + "\n" for line in kept))  # a crash here keeps the old log


def learning_rate(config: TrainConfig, step: int) -> float:
    """Linear warm-up to `lr` (over warmup_steps, at most a tenth of the run), then a cosine down to
    lr * min_lr_ratio at `steps`."""
    warmup = min(config.warmup_steps, max(1, config.steps // 10))
    if step < warmup:
        return config.lr * (step + 1) / warmup
    span = max(1, config.steps - warmup)
    progress = min(1.0, (step - warmup) / span)
    return config.lr * (config.min_lr_ratio + (1 - config.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress)))


def _optimizer(module: nn.Module, config: TrainConfig) -> torch.optim.Optimizer:
    """AdamW; matrices decay, vectors do not, nor the parameters a module names in its NO_WEIGHT_DECAY
    (positions, such as the grounding anchor's places, which decay would pull toward the origin); in a
    joint run System 1's instruction grounding learns at `grounding_lr_scale` times the run's learning
    rate (each group's "lr_scale")."""
    scaled = config.grounding_phase == "joint"
    undecayed = {f"{prefix}.{name}" if prefix else name
                 for prefix, sub in module.named_modules() for name in getattr(sub, "NO_WEIGHT_DECAY", ())}
    groups: dict[tuple[bool, bool], list[nn.Parameter]] = {}
    for name, p in module.named_parameters():
        if p.requires_grad:
            decay = p.dim() >= 2 and name not in undecayed
            groups.setdefault((decay, scaled and name.startswith("grounding.")), []).append(p)
    return torch.optim.AdamW(
        [{"params": params, "weight_decay": config.weight_decay if decay else 0.0,
          "lr_scale": config.grounding_lr_scale if grounding else 1.0}
         for (decay, grounding), params in sorted(groups.items(), key=lambda kv: (not kv[0][0], kv[0][1]))],
        lr=config.lr, betas=(config.beta1, config.beta2),
    )


# ---------------------------------------------------------------------------------------------
# Data per stage


def _prepare_data(config: TrainConfig, model: TriVLA, readers: list, env: DistEnv) -> tuple[Any, Callable, dict]:
    """(dataset, collate function, summary) of the stage; caches are made here (sharded over ranks).
    `readers`: --data's dataset, then --extra-data's (policy stage); empty for the vlm stage."""
    from trivla_drake.train import datasets as ds

    progress = config.progress and env.is_main
    reader = readers[0] if readers else None
    if config.stage == "video":
        episodes = list(range(reader.num_episodes))
        dyn = model.config.dynamics
        store = ds.FrameStore(reader, [config.static_camera, config.wrist_camera], dyn.video_size,
                              Path(config.cache_dir) / "clips")
        missing = env.broadcast_object(store.missing(episodes))  # rank 0's list: ranks split the same work
        from tqdm import tqdm

        for episode, camera in tqdm(missing[env.rank :: env.world_size], desc="decoding clips", unit="video",
                                    disable=not progress or not missing):
            store.make(episode, camera)
        env.barrier()
        stride = config.future_stride or ds.clip_stride(reader.fps, dyn.num_frames, config.clip_seconds)
        dataset = ds.VideoClipDataset(store, episodes, dyn.num_frames, stride)
        return dataset, ds.collate_video, {
            "episodes": len(episodes), "samples": len(dataset), "future_stride": stride,
            "clip_seconds": (dyn.num_frames - 1) * stride / reader.fps, "clip_cache": str(store.root),
            "clip_videos_decoded": len(missing),
        }
    if config.stage == "vlm":
        from trivla_drake.train import vqa

        folder = vqa_folder(config, model)
        settings = vqa.vqa_settings(scenes=config.vqa_scenes, questions_per_scene=config.vqa_questions_per_scene,
                                    seed=config.vqa_seed, image_size=model.image_size)
        error = None
        if env.is_main:
            try:
                vqa.ensure_vqa_set(folder, settings, progress=progress)
            except Exception as exc:  # noqa: BLE001 - re-raised on every rank below
                error = f"{type(exc).__name__}: {exc}"
        error = env.broadcast_object(error)
        if error is not None:
            raise ValueError(f"cannot make the VQA set in {folder}: {error}")
        dataset = vqa.VQADataset(folder, "train")
        return dataset, vqa.collate_vqa, {"vqa_folder": str(folder), "samples": len(dataset)}
    # policy
    from trivla_drake.train.features import ensure_feature_cache

    from trivla_drake.train.dataset_union import PolicyDatasetUnion, check_each_folder_adds, drop_repeated_episodes

    chosen = [list(range(r.num_episodes)) for r in readers]
    chosen, repeated = drop_repeated_episodes(readers, chosen)
    parts, summary = [], {}
    check_each_folder_adds(readers, chosen)
    for r, episodes in zip(readers, chosen):
        shards, summary_r = ensure_feature_cache(model, r, episodes, config, env, progress=progress)
        for key, value in summary_r.items():  # shard counts add up; the rest (one cache folder) is the first's
            if key not in summary:
                summary[key] = value
            elif key.startswith("feature_shards_"):
                summary[key] += value
        parts.append(ds.PolicyFeatureDataset(
            r, episodes, shards, feature_stride=config.feature_stride,
            action_horizon=model.config.policy.action_horizon,
            use_system2=model.vision_language is not None, use_system3=model.dynamics is not None,
            grounding_frames_only=config.grounding_phase == "bind",
            grounding_carry_tasks=tuple(config.grounding_carry_tasks),
        ))
    dataset = parts[0] if len(parts) == 1 else PolicyDatasetUnion(parts)
    if len(parts) > 1:
        summary["episodes_per_dataset"] = {str(r.root): len(e) for r, e in zip(readers, chosen)}
        summary["repeated_episodes_dropped"] = repeated
    return dataset, ds.collate_policy, {"episodes": sum(map(len, chosen)), "samples": len(dataset), **summary}


def vqa_folder(config: TrainConfig, model: TriVLA) -> Path:
    """Where the vlm stage's VQA set lives: `data` unless that is a LeRobot dataset, else the cache."""
    from trivla_drake.train import vqa

    if config.data and not (Path(config.data) / "meta" / "info.json").is_file():
        return Path(config.data)
    if config.data and int(os.environ.get("RANK", "0")) == 0:
        print(f"trivla-drake train: note: {config.data} is a LeRobot dataset; the vlm stage renders its own "
              "scenes and does not use it", file=sys.stderr)
    settings = vqa.vqa_settings(scenes=config.vqa_scenes, questions_per_scene=config.vqa_questions_per_scene,
                                seed=config.vqa_seed, image_size=model.image_size)
    return Path(config.cache_dir) / "vqa" / vqa.vqa_key(settings)


# ---------------------------------------------------------------------------------------------
# The run


def train(config: TrainConfig, *, step_callback: StepCallback | None = None) -> dict[str, Any]:
    """Runs one stage (see the module doc); returns a summary (also written to OUT/summary.json).
    `step_callback(step)` is called after every step, once its checkpoint (if any) is written."""
    config = config.resolved()
    env = setup_distributed(config.dist_timeout_minutes)
    try:
        return _train(config, env, step_callback)
    finally:
        teardown_distributed(env)


def _train(config: TrainConfig, env: DistEnv, step_callback: StepCallback | None) -> dict[str, Any]:
    from tqdm import tqdm

    if config.threads is not None:
        torch.set_num_threads(config.threads)
    out = Path(config.out)
    latest = ckpt.latest_checkpoint(out)
    resume_from = None
    if latest is not None and not config.resume:
        raise ValueError(f"{out} already holds a training run (newest checkpoint: {latest}); "
                         "pass --resume to continue it, or choose another --out")
    if config.resume and latest is not None:
        latest, skipped = ckpt.newest_intact_checkpoint(out, set_aside=env.is_main)
        if latest is None:
            raise ValueError(f"cannot resume {out}: no checkpoint of it is intact ("
                             + "; ".join(f"{path}: {why}" for path, why, _ in skipped)
                             + "); start a new run with another --out")
        for path, why, kept in skipped:
            _note(env, f"warning: skipping checkpoint {path} ({why}); resuming from the newest intact one, {latest} "
                       f"(the broken one is kept, as {kept})")
        saved = ckpt.load_train_config(latest)
        if config.preset is None:
            config = dataclasses.replace(config, preset=saved.preset)
        check_resume_compatible(saved, config)
        resume_from = latest
    else:
        if config.resume:
            _note(env, f"nothing to resume in {out}; starting a new run")
        config = dataclasses.replace(config, preset=_resolve_preset(config))
        if config.stage == "policy" and not config.init and (config.use_system2 or config.use_system3):
            _note(env, "the policy stage starts from a fresh preset: Systems 2 and 3 are untrained "
                       "(pass --init with the vlm stage's final checkpoint)")
    config.validate()

    reader, readers = None, []
    if config.stage in ("video", "policy"):
        from trivla_drake.data.lerobot import LeRobotReader

        reader = LeRobotReader(config.data)
        readers = [reader, *(LeRobotReader(folder) for folder in config.extra_data)]
    model = build_model(config, resume_from)
    train_state = ckpt.load_train_state(resume_from) if resume_from is not None else None
    if config.stage == "policy":
        from trivla_drake.train.datasets import check_spaces, narrowed_action_ranges

        where = f"checkpoint {resume_from}" if resume_from else (f"--init checkpoint {config.init}" if config.init
                                                                 else f"preset {config.preset!r}")
        from trivla_drake.train.dataset_union import check_same_features, check_same_fps, union_normalization
        from trivla_drake.train.datasets import check_cameras

        for one in readers:
            check_spaces(one, model.config, where)
            if model.policy.grounding is not None:
                check_grounding(one, config.grounding_weight, where)
            if model.vision_language is not None or model.dynamics is not None:
                check_cameras(one, [config.static_camera, config.wrist_camera])
        check_same_fps(readers)
        check_same_features(readers)
        fitted = union_normalization(readers, model.config)
        if train_state is not None:
            check_resumed_normalization(model.normalization, fitted, where)
        if config.init and train_state is None:
            narrowed = narrowed_action_ranges(model.normalization, fitted, model.config.action_names)
            if narrowed:
                _note(env, f"--data's action ranges are narrower than {where}'s, so its outputs are rescaled: "
                           f"{'; '.join(narrowed)}")
        model.set_normalization(fitted)

    torch.manual_seed(config.seed)
    model.requires_grad_(False)
    trained = trainable_module(model, config.stage)
    trained.requires_grad_(True)
    if config.stage == "policy" and config.grounding_phase != "joint":
        binding = model.policy.binding_parameters()  # bind trains only these; follow all but these
        trained_in_bind = model.policy.held_parameters() if config.bind_held_only else binding
        for name, p in model.policy.named_parameters():
            p.requires_grad_(name in trained_in_bind if config.grounding_phase == "bind" else name not in binding)
    if config.stage == "vlm" and model.vision_language.block_head is not None and not config.dense_weight:
        model.vision_language.block_head.requires_grad_(False)  # no dense loss: the head gets no gradient
    model.to(env.device)
    model.eval()
    trained.train()

    prepare_started = time.time()
    for one in readers:  # a corrupted or replaced data / video file stops the run before any caching, naming it
        one.verify_files()
    dataset, collate, data_summary = _prepare_data(config, model, readers, env)
    # A resumed run keeps its checkpoint's statistics, a follow run its bind run's (what the binding learnt on),
    # and a held-only bind its --init's (everything but the held-block read-out stays as it was).
    if (config.stage == "policy" and train_state is None and config.grounding_phase != "follow"
            and not config.bind_held_only):
        from trivla_drake.train.feature_statistics import fit_feature_standardizers

        data_summary.update(fit_feature_standardizers(model, dataset.shards, progress=config.progress and env.is_main))
    data_summary["data_prepare_s"] = time.time() - prepare_started
    start_step = int(train_state["step"]) if train_state else 0
    if train_state and train_state.get("world_size") != env.world_size:
        _note(env, f"resuming a run of {train_state.get('world_size')} processes with {env.world_size}; "
                   "the data order from here differs from an uninterrupted run")

    from trivla_drake.train.sampler import StepBatchSampler

    sampler = StepBatchSampler(len(dataset), config.batch_size, seed=config.seed, rank=env.rank,
                               world_size=env.world_size, start_step=start_step, total_steps=config.steps)
    loader = torch.utils.data.DataLoader(dataset, batch_sampler=sampler, collate_fn=collate,
                                         num_workers=config.workers, persistent_workers=False)
    optimizer = _optimizer(trained, config)
    generator = torch.Generator().manual_seed(_rank_seed(config.seed, env.rank))
    if train_state is not None:
        optimizer.load_state_dict(train_state["optimizer"])
        rng = train_state["rng"]
        _set_rng_state(rng[env.rank] if env.rank < len(rng) else rng[0], generator)
        if env.rank >= len(rng):
            generator.manual_seed(_rank_seed(config.seed, env.rank) + start_step)
    average = WeightAverage(model, config.ema_decay) if config.ema_decay > 0 else None
    if average is not None and train_state is not None:
        if "weight_average" not in train_state:
            raise ValueError(f"cannot resume {resume_from}: it holds no weight average")
        average.load_state_dict(train_state["weight_average"])  # and the trained weights back into the model
    loss_module = StageLoss(model, config.stage, generator, config.dense_weight, config.grounding_weight,
                            config.grounding_phase)
    runner: nn.Module = loss_module
    if env.distributed:
        runner = nn.parallel.DistributedDataParallel(
            loss_module, device_ids=[env.device.index] if env.device.type == "cuda" else None,
            find_unused_parameters=False,  # every trained weight gets a gradient in all three losses
        )
    params = [p for p in trained.parameters() if p.requires_grad]
    autocast = env.device.type == "cuda" and config.precision == "bf16"

    log_path = out / "log.jsonl"
    if env.is_main:
        out.mkdir(parents=True, exist_ok=True)
        _truncate_log(log_path, start_step)  # lines of steps after the resumed checkpoint are redone
    bar = tqdm(total=config.steps, initial=start_step, desc=f"train {config.stage}", unit="step",
               disable=not (config.progress and env.is_main), dynamic_ncols=True)
    loss_ema = train_state.get("loss_ema") if train_state else None
    step = start_step
    step_times: list[float] = []
    started = time.time()

    def weights_for_checkpoints():
        return average.swapped_in() if average is not None else contextlib.nullcontext()

    def save(at_step: int) -> None:
        states = env.all_gather_object(_rng_state(generator))
        if env.is_main:
            state = {"step": at_step, "optimizer": optimizer.state_dict(), "rng": states,
                     "world_size": env.world_size, "loss_ema": loss_ema}
            if average is not None:
                state["weight_average"] = average.state_dict()
            with weights_for_checkpoints():  # the model a checkpoint holds: the average, if there is one
                ckpt.write_checkpoint(out / ckpt.CHECKPOINTS_DIR / ckpt.step_dir_name(at_step), model=model,
                                      train_state=state, config=config)
            ckpt.prune_checkpoints(out, config.keep_checkpoints)
        env.barrier()

    try:
        tick = time.time()
        for batch in loader:
            lr = learning_rate(config, step)
            for group in optimizer.param_groups:
                group["lr"] = lr * group.get("lr_scale", 1.0)
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=autocast):
                loss, info = runner(batch)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if config.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, config.grad_clip)
            optimizer.step()
            if average is not None:
                average.update()
            step += 1
            mean_loss = env.mean(float(loss.detach()))
            if not math.isfinite(mean_loss):
                raise FloatingPointError(f"the loss became {mean_loss} at step {step}; lower --lr")
            loss_ema = mean_loss if loss_ema is None else 0.98 * loss_ema + 0.02 * mean_loss
            now = time.time()
            step_times.append(now - tick)
            tick = now
            bar.update(1)
            bar.set_postfix(loss=f"{mean_loss:.4f}", ema=f"{loss_ema:.4f}", lr=f"{lr:.2e}")
            if env.is_main and (step % config.log_every == 0 or step == config.steps):
                with open(log_path, "a") as f:
                    f.write(json.dumps({"step": step, "loss": mean_loss, "loss_ema": loss_ema, "lr": lr,
                                        "step_time_s": step_times[-1], **{k: v for k, v in info.items()
                                                                          if k != "loss"}}) + "\n")
            if step % config.checkpoint_every == 0 or step == config.steps:
                save(step)
            if step_callback is not None:
                step_callback(step)
    finally:
        bar.close()

    if ckpt.latest_checkpoint(out) is None or ckpt.read_step(ckpt.latest_checkpoint(out)) < step:
        save(step)  # nothing was saved yet (e.g. a run resumed at its last step)
    summary: dict[str, Any] = {
        "stage": config.stage, "preset": config.preset, "steps": step, "resumed_from_step": start_step,
        "world_size": env.world_size, "batch_size_per_process": config.batch_size,
        "loss_ema": loss_ema, "wall_s": time.time() - started,
        "step_time_s": float(np.median(step_times[1:] or step_times)) if step_times else None,
        **data_summary,
    }
    if config.stage == "vlm" and env.is_main and config.vqa_eval_questions > 0:
        from trivla_drake.train import vqa

        eval_started = time.time()
        with weights_for_checkpoints():
            summary.update(vqa.evaluate_vqa(model, vqa.VQADataset(data_summary["vqa_folder"], "eval"),
                                            batch_size=config.batch_size, max_questions=config.vqa_eval_questions))
        summary["vqa_eval_s"] = time.time() - eval_started
    env.barrier()
    summary["weights_sha256_per_rank"] = env.all_gather_object(weights_digest(model))
    if env.is_main:
        newest = ckpt.latest_checkpoint(out)
        if newest != out / ckpt.FINAL_DIR:
            ckpt.copy_checkpoint(newest, out / ckpt.FINAL_DIR)
        summary["final_checkpoint"] = str(out / ckpt.FINAL_DIR)
        if log_path.exists():
            from trivla_drake.train.loss_plot import plot_training_curve

            plot = plot_training_curve(log_path, out / "loss.png", title=f"{config.stage} stage, {out.name}")
            if plot is not None:
                summary["loss_plot"] = str(plot)
        (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    env.barrier()
    return summary
