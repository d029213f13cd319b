"""The model a training run starts from: a resumed checkpoint, the `init` checkpoint with the run's System 1 / System 2
options added (`apply_ablations`, `replace_system2`), or a fresh `preset` model; and what each stage trains."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
from torch import nn

from trivla_drake.nn.checkpoint import load_checkpoint, read_checkpoint_config
from trivla_drake.nn.config import TriVLAConfig, text_encoder_feeds
from trivla_drake.nn.presets import PRESETS, make_config
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig

# System 1's state MLP reads the tool-centre-point pose computed from the joint angles (policy.tcp_features):
# every run adds it where its start has none (the switch to leave it out went with the experiments).
TCP_FEATURES = True

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
                f"set use_system{name[-1]} false or start from a checkpoint that has it"
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
                 tokenizers=tokenizers, load_pretrained=False, text_encoder=model.text_encoder)
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
    _check_same_instruction_reader(model, donor, where)
    if mine.config.drop_unused_llm_layers:
        theirs.drop_layers_above_readout()
    model.vision_language = theirs.to(model.device)
    model.config = dataclasses.replace(model.config, vision_language=theirs.config)
    return model


def _check_same_instruction_reader(model: TriVLA, donor: TriVLA, where: str) -> None:
    """ValueError unless both System 2s read the instruction alike: both embed its tokens themselves, or both read
    the states of the same pretrained text encoder (`TriVLAConfig.text_encoder`, by content hash)."""
    def reader(m: TriVLA) -> str | None:
        return m.text_encoder.content_hash if text_encoder_feeds(m.config, 2) else None

    mine, theirs = reader(model), reader(donor)
    if mine == theirs:
        return

    def words(m: TriVLA, digest: str | None) -> str:
        return ("embeds the instruction's tokens itself" if digest is None else
                f"reads the text encoder {m.config.text_encoder!r} (content sha256 {digest[:12]}…)")
    raise ValueError(f"{where}: its System 2 {words(donor, theirs)}, the --init model's {words(model, mine)}: "
                     "replace System 2 only with one that reads the instruction as the --init model's does")


def resolve_preset(config: TrainConfig) -> str:
    if config.policy.system2_from is not None and not Path(config.policy.system2_from).is_dir():
        raise FileNotFoundError(f"policy.system2_from {config.policy.system2_from!r} is not a checkpoint directory")
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

    return len(BLOCK_COLORS) if config.vlm.dense_weight > 0 else 0


def fresh_model_config(config: TrainConfig) -> TriVLAConfig:
    """The `preset` model a run without --init or resume builds (with the tcp features, as every preset), with the
    run's options. A vlm run
    keeps every LLM layer (a preset may build only those up to the read-out, as `paper` does):
    its answers are read from the LLM's last layer, not from Q_vl."""
    cfg = make_config(config.preset, init_seed=config.seed,
                      use_system2=config.use_system2, use_system3=config.use_system3)
    vision_language = cfg.vision_language
    return dataclasses.replace(
        cfg, policy=dataclasses.replace(cfg.policy,
                                        vl_position_embedding=config.policy.vl_position_embedding and config.use_system2,
                                        instruction_grounding=config.policy.grounding.weight > 0,
                                        subgoal_offset=config.policy.subgoal_offset,
                                        grounding_reads_gripper=config.policy.grounding.reads_gripper),
        vision_language=dataclasses.replace(
            vision_language, dense_classes=_dense_classes(config) if config.use_system2 else 0,
            dense_subcells=config.vlm.dense_subcells or 1,
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
        if config.policy.grounding.phase == "follow" and model.policy.grounding is None:
            raise ValueError(f"policy.grounding.phase follow keeps the instruction grounding of its "
                             f"{where}, which has none: train one with policy.grounding.phase bind first")
        if (config.policy.grounding.phase == "follow" and config.policy.grounding.reads_gripper
                and not model.config.policy.grounding_reads_gripper):
            raise ValueError(f"policy.grounding.reads_gripper changes the instruction grounding, "
                             f"which a follow run keeps as its {where} has it (reading no gripper): bind one with "
                             f"policy.grounding.reads_gripper first")
        if config.policy.grounding.keep and model.policy.grounding is None:
            raise ValueError(f"policy.grounding.keep continues the instruction grounding of its {where}, "
                             f"which has none: bind one without policy.grounding.keep first")
        model = apply_ablations(model, config.use_system2, config.use_system3, where, TCP_FEATURES,
                                config.policy.vl_position_embedding, _dense_classes(config), config.policy.grounding.weight > 0,
                                config.policy.subgoal_offset, config.vlm.dense_subcells if config.vlm.dense_weight > 0 else None,
                                config.policy.grounding.reads_gripper)
        if config.policy.system2_from is not None:
            model = replace_system2(model, load_checkpoint(config.policy.system2_from), f"policy.system2_from {config.policy.system2_from}")
        if config.policy.fresh_system1:
            model.reset_system1(config.seed, keep_binding=config.policy.grounding.phase == "follow")
        if config.policy.grounding.phase == "bind" and not config.policy.grounding.keep:
            # A bind run learns the binding from a fresh grounding (a resumed one keeps its own): one
            # from a joint run stayed at chance when bound further, a fresh one bound
            # (research/instruction_grounding).
            torch.manual_seed(config.seed)
            model.policy.reset_grounding()
    else:
        if config.policy.grounding.phase == "follow":
            raise ValueError("policy.grounding.phase follow keeps the instruction grounding of its "
                             "--init checkpoint: pass --init with a policy.grounding.phase bind run's checkpoint")
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
                         f"(export with drop_unused_llm_layers false)")
    if model.config.policy.tcp_features != TCP_FEATURES:
        raise ValueError(f"{where} has policy.tcp_features = {model.config.policy.tcp_features}: every run of this "
                         f"code trains with the tcp features")
    return model



def trainable_module(model: TriVLA, stage: str) -> nn.Module:
    """What a stage trains: System 3's UNet and text projection (its VAE and CLIP stay frozen, as in
    VPP), all of System 2, or System 1."""
    if stage == "video":
        return nn.ModuleList([model.dynamics.unet, model.dynamics.text_projection])
    if stage == "vlm":
        return model.vision_language
    return model.policy

