"""Builders of the library components (SigLIP, Llama, CLIP text, SVD UNet and VAE): from our config
dataclasses with random weights, from a checkpoint's recorded component configs, or from local
pretrained directories with `from_pretrained` (never downloading: `local_files_only=True`)."""

from __future__ import annotations

import importlib.util
import json
import os
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from trivla_drake.nn.config import (
    LanguageModelConfig,
    TextEncoderConfig,
    VideoAutoencoderConfig,
    VideoUNetConfig,
    VisionEncoderConfig,
)

# ---------------------------------------------------------------------------------------------
# Library configs from our dataclasses


def siglip_vision_config(cfg: VisionEncoderConfig):
    """transformers `SiglipVisionConfig` for our SigLIP shape (no pooling head: Eagle-2 uses the tokens)."""
    from transformers import SiglipVisionConfig

    return SiglipVisionConfig(
        image_size=cfg.image_size,
        patch_size=cfg.patch_size,
        hidden_size=cfg.hidden_size,
        intermediate_size=cfg.intermediate_size,
        num_hidden_layers=cfg.num_hidden_layers,
        num_attention_heads=cfg.num_attention_heads,
        layer_norm_eps=cfg.layer_norm_eps,
        vision_use_head=False,
    )


def llama_config(cfg: LanguageModelConfig, *, num_hidden_layers: int | None = None, pad_token_id: int = 0):
    """transformers `LlamaConfig` for our LLM shape, optionally truncated to `num_hidden_layers`."""
    from transformers import LlamaConfig

    return LlamaConfig(
        vocab_size=cfg.vocab_size,
        hidden_size=cfg.hidden_size,
        intermediate_size=cfg.intermediate_size,
        num_hidden_layers=num_hidden_layers or cfg.num_hidden_layers,
        num_attention_heads=cfg.num_attention_heads,
        num_key_value_heads=cfg.num_key_value_heads,
        rope_theta=cfg.rope_theta,
        rms_norm_eps=cfg.rms_norm_eps,
        max_position_embeddings=cfg.max_position_embeddings,
        tie_word_embeddings=cfg.tie_word_embeddings,
        pad_token_id=pad_token_id,
        bos_token_id=None,
        eos_token_id=None,
        use_cache=False,
    )


def clip_text_config(cfg: TextEncoderConfig, *, pad_token_id: int, bos_token_id: int, eos_token_id: int):
    """transformers `CLIPTextConfig` for our text-encoder shape."""
    from transformers import CLIPTextConfig

    return CLIPTextConfig(
        vocab_size=cfg.vocab_size,
        hidden_size=cfg.hidden_size,
        intermediate_size=cfg.intermediate_size,
        num_hidden_layers=cfg.num_hidden_layers,
        num_attention_heads=cfg.num_attention_heads,
        max_position_embeddings=cfg.max_position_embeddings,
        projection_dim=cfg.hidden_size,
        pad_token_id=pad_token_id,
        bos_token_id=bos_token_id,
        eos_token_id=eos_token_id,
    )


def svd_unet_config(cfg: VideoUNetConfig, *, latent_channels: int, num_frames: int) -> dict[str, Any]:
    """Keyword config of diffusers `UNetSpatioTemporalConditionModel` (input: noise + condition latents)."""
    return dict(
        in_channels=2 * latent_channels,
        out_channels=latent_channels,
        down_block_types=tuple(cfg.down_block_types),
        up_block_types=tuple(cfg.up_block_types),
        block_out_channels=tuple(cfg.block_out_channels),
        layers_per_block=cfg.layers_per_block,
        cross_attention_dim=cfg.cross_attention_dim,
        num_attention_heads=tuple(cfg.num_attention_heads),
        addition_time_embed_dim=cfg.addition_time_embed_dim,
        projection_class_embeddings_input_dim=3 * cfg.addition_time_embed_dim,
        num_frames=num_frames,
    )


def svd_vae_config(cfg: VideoAutoencoderConfig) -> dict[str, Any]:
    """Keyword config of diffusers `AutoencoderKLTemporalDecoder`."""
    return dict(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * len(cfg.block_out_channels),
        block_out_channels=tuple(cfg.block_out_channels),
        layers_per_block=cfg.layers_per_block,
        latent_channels=cfg.latent_channels,
        scaling_factor=cfg.scaling_factor,
    )


# ---------------------------------------------------------------------------------------------
# Components from recorded configs (what a checkpoint stores)


def component_config_dict(module: nn.Module) -> dict[str, Any]:
    """The JSON-able library config of a transformers or diffusers module, to rebuild it later."""
    config = module.config
    if hasattr(config, "to_dict"):
        data = config.to_dict()
    else:  # diffusers FrozenDict
        data = {k: v for k, v in dict(config).items() if not k.startswith("_")}
    return json.loads(json.dumps(data, default=list))


def build_siglip_vision(config) -> nn.Module:
    """A randomly initialised `SiglipVisionModel` from a `SiglipVisionConfig` or its dict."""
    from transformers import SiglipVisionConfig, SiglipVisionModel

    if isinstance(config, dict):
        config = SiglipVisionConfig.from_dict(config)
    return SiglipVisionModel(config)


def build_llama(config) -> nn.Module:
    """A randomly initialised `LlamaForCausalLM` from a `LlamaConfig` or its dict."""
    from transformers import LlamaConfig, LlamaForCausalLM

    if isinstance(config, dict):
        config = LlamaConfig.from_dict(config)
    return LlamaForCausalLM(config)


def build_clip_text(config) -> nn.Module:
    """A randomly initialised `CLIPTextModel` from a `CLIPTextConfig` or its dict."""
    from transformers import CLIPTextConfig, CLIPTextModel

    if isinstance(config, dict):
        config = CLIPTextConfig.from_dict(config)
    return CLIPTextModel(config)


def build_svd_unet(config: dict[str, Any]) -> nn.Module:
    """A randomly initialised `UNetSpatioTemporalConditionModel` from its keyword config."""
    from diffusers import UNetSpatioTemporalConditionModel

    return UNetSpatioTemporalConditionModel.from_config(config)


def build_svd_vae(config: dict[str, Any]) -> nn.Module:
    """A randomly initialised `AutoencoderKLTemporalDecoder` from its keyword config."""
    from diffusers import AutoencoderKLTemporalDecoder

    return AutoencoderKLTemporalDecoder.from_config(config)


def eagle_projector(vision_hidden: int, llm_hidden: int, ratio: float) -> nn.Sequential:
    """Eagle-2's `mlp1`: LayerNorm-Linear-GELU-Linear from pixel-shuffled vision tokens to LLM width."""
    fold = round(1 / ratio) ** 2
    return nn.Sequential(
        nn.LayerNorm(vision_hidden * fold),
        nn.Linear(vision_hidden * fold, llm_hidden),
        nn.GELU(),
        nn.Linear(llm_hidden, llm_hidden),
    )


# ---------------------------------------------------------------------------------------------
# Local pretrained directories


def _require_dir(path: str, what: str) -> None:
    if not os.path.isdir(path):
        raise ValueError(f"{what} path {path!r} is not a directory (pretrained weights are never downloaded)")


def _diffusers_load_kwargs() -> dict[str, Any]:
    # diffusers' low-memory loading needs `accelerate`; without it, ask for plain loading (no warning).
    return {"local_files_only": True, "low_cpu_mem_usage": importlib.util.find_spec("accelerate") is not None}


def _subfolder(path: str, name: str) -> str:
    """`path/name` when it exists (the layout of the released SVD repo), else `path`."""
    sub = os.path.join(path, name)
    return sub if os.path.isfile(os.path.join(sub, "config.json")) else path


def load_siglip_vision(path: str) -> nn.Module:
    """`SiglipVisionModel` from a local SigLIP (or SigLIP vision-only) directory."""
    from transformers import SiglipVisionModel

    _require_dir(path, "SigLIP")
    # Eagle-2 reads the patch tokens; the attention-pooling head would be dead weight.
    return SiglipVisionModel.from_pretrained(path, local_files_only=True, vision_use_head=False)


def load_llama(path: str, *, num_hidden_layers: int | None = None) -> nn.Module:
    """`LlamaForCausalLM` (e.g. SmolLM2) from a local directory, optionally keeping only the first layers."""
    from transformers import LlamaForCausalLM

    _require_dir(path, "LLM")
    kwargs = {"num_hidden_layers": num_hidden_layers} if num_hidden_layers else {}
    return LlamaForCausalLM.from_pretrained(path, local_files_only=True, **kwargs)


def load_clip_text(path: str) -> nn.Module:
    """`CLIPTextModel` from a local CLIP (or CLIP text-only) directory."""
    from transformers import CLIPTextModel

    _require_dir(path, "CLIP text encoder")
    return CLIPTextModel.from_pretrained(_subfolder(path, "text_encoder"), local_files_only=True)


def load_svd_unet(path: str) -> nn.Module:
    """SVD's `UNetSpatioTemporalConditionModel` from a local SVD repo (its `unet/`) or UNet directory."""
    from diffusers import UNetSpatioTemporalConditionModel

    _require_dir(path, "SVD UNet")
    return UNetSpatioTemporalConditionModel.from_pretrained(_subfolder(path, "unet"), **_diffusers_load_kwargs())


def load_svd_vae(path: str) -> nn.Module:
    """SVD's `AutoencoderKLTemporalDecoder` from a local SVD repo (its `vae/`) or VAE directory."""
    from diffusers import AutoencoderKLTemporalDecoder

    _require_dir(path, "SVD VAE")
    return AutoencoderKLTemporalDecoder.from_pretrained(_subfolder(path, "vae"), **_diffusers_load_kwargs())


@dataclass
class Eagle2Parts:
    """The three parts of an Eagle-2 checkpoint as our modules."""

    vision_encoder: nn.Module
    projector: nn.Sequential
    llm: nn.Module
    pixel_shuffle_ratio: float


def _read_safetensors_dir(path: str) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    files = sorted(f for f in os.listdir(path) if f.endswith(".safetensors"))
    if not files:
        raise ValueError(f"no *.safetensors weights in {path!r}")
    state: dict[str, torch.Tensor] = {}
    for name in files:
        state.update(load_file(os.path.join(path, name)))
    return state


def _strip_legacy_prefix(state: dict[str, torch.Tensor], module: nn.Module, prefix: str) -> dict[str, torch.Tensor]:
    """Drops `prefix` from keys when `module` does not use it (transformers 4.x nested SigLIP as
    `vision_model.*`; 5.x keeps its parts at the top level)."""
    expected = set(module.state_dict())
    if any(k in expected for k in state) or not all(k.startswith(prefix) for k in state):
        return state
    return {k[len(prefix) :]: v for k, v in state.items()}


def load_eagle2(path: str, *, num_hidden_layers: int | None = None) -> Eagle2Parts:
    """Eagle-2 (SigLIP + MLP projector + Llama-family LLM) from a local directory holding its config.json
    (`vision_config`, `llm_config`, `downsample_ratio`) and safetensors with the keys `vision_model.*`,
    `mlp1.*`, `language_model.*` of the released checkpoint; the LLM may be cut to its first layers."""
    from transformers import LlamaConfig, SiglipVisionConfig

    _require_dir(path, "Eagle-2")
    with open(os.path.join(path, "config.json")) as f:
        meta = json.load(f)
    for key in ("vision_config", "llm_config"):
        if key not in meta:
            raise ValueError(f"Eagle-2 config {path}/config.json has no {key!r}")
    llm_type = meta["llm_config"].get("model_type", "llama")
    if llm_type != "llama":
        raise ValueError(
            f"Eagle-2 checkpoint {path!r} has a {llm_type!r} LLM; only Llama-family (SmolLM2) LLMs are supported"
        )
    if meta.get("ps_version", "v2") != "v2":
        raise ValueError(f"Eagle-2 checkpoint {path!r} has ps_version {meta['ps_version']!r}; only 'v2' pixel "
                         "shuffles are supported (v1 orders the token grid transposed)")
    if meta.get("select_layer", -1) != -1:
        raise ValueError("only Eagle-2 checkpoints that read the last SigLIP layer (select_layer -1) are supported")
    vision_cfg = SiglipVisionConfig.from_dict({**meta["vision_config"], "vision_use_head": False})
    llm_dict = dict(meta["llm_config"])
    if num_hidden_layers:
        llm_dict["num_hidden_layers"] = num_hidden_layers
    llm_cfg = LlamaConfig.from_dict(llm_dict)
    ratio = float(meta.get("downsample_ratio", 0.5))

    vision = build_siglip_vision(vision_cfg)
    llm = build_llama(llm_cfg)
    projector = eagle_projector(vision_cfg.hidden_size, llm_cfg.hidden_size, ratio)

    state = _read_safetensors_dir(path)
    parts = {"vision_model.": {}, "mlp1.": {}, "language_model.": {}}
    for key, value in state.items():
        for prefix, bucket in parts.items():
            if key.startswith(prefix):
                bucket[key[len(prefix) :]] = value
    keep = set(llm.state_dict())
    llm_state = {k: v for k, v in parts["language_model."].items() if k in keep}
    vision_state = _strip_legacy_prefix(parts["vision_model."], vision, "vision_model.")
    for module, sub, what in (
        (vision, vision_state, "vision_model"),
        (projector, parts["mlp1."], "mlp1"),
    ):
        result = module.load_state_dict(sub, strict=False)
        if result.missing_keys:
            raise ValueError(f"Eagle-2 weights in {path!r} lack {what} keys {result.missing_keys[:5]}")
    result = llm.load_state_dict(llm_state, strict=False)
    missing = [k for k in result.missing_keys if not (k == "lm_head.weight" and llm_cfg.tie_word_embeddings)]
    if missing:
        raise ValueError(f"Eagle-2 weights in {path!r} lack language_model keys {missing[:5]}")
    if llm_cfg.tie_word_embeddings:
        llm.tie_weights()
    return Eagle2Parts(vision_encoder=vision, projector=projector, llm=llm, pixel_shuffle_ratio=ratio)
