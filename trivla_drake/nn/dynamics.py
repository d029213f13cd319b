"""System 3, the dynamics perception module: SVD's spatio-temporal UNet in a video VAE's latent space,
conditioned on the current frame (its latent, concatenated on channels as SVD does) and a CLIP text
embedding of the instruction (cross-attention, as VPP does).

Training (eq. 1): reconstruct the whole clip x_0 = s_0:T from its noised version.
Inference (eq. 2-3): ONE UNet pass at the final noise level on pure-noise latents; the outputs of the
first `feature_up_blocks` up-sampling blocks are linearly interpolated to W_p x H_p and concatenated
on channels, F_p (T, sum C_m, H_p, W_p). The later up-blocks and conv_out never run.

With a pretrained text encoder entering System 3 (`TriVLAConfig.text_encoder`) there is no CLIP text encoder:
the conditioning is that encoder's sentence embedding then its token states, zero-padded to `text_max_tokens`
(`text_encoder.sentence_then_tokens`), projected to the UNet's cross-attention width.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from trivla_drake.nn import noise_schedule, pretrained
from trivla_drake.nn.config import DynamicsConfig
from trivla_drake.nn.early_exit import run_until
from trivla_drake.nn.tokenizer import TextTokenizer


def frames_to_vae_input(frames: torch.Tensor, size: int, dtype: torch.dtype) -> torch.Tensor:
    """uint8 (N, H, W, 3) -> float (N, 3, size, size) in [-1, 1], resized with antialiased bilinear."""
    x = frames.permute(0, 3, 1, 2).to(torch.float32) / 255.0
    if x.shape[-1] != size or x.shape[-2] != size:
        x = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    return (x * 2.0 - 1.0).to(dtype)


class DynamicsPerceptionModule(nn.Module):
    """System 3: video VAE + CLIP text encoder + SVD UNet, read out in one pass from its up-blocks."""

    def __init__(
        self,
        config: DynamicsConfig,
        tokenizer: TextTokenizer,
        vae: nn.Module,
        text_encoder: nn.Module | None,
        unet: nn.Module,
        pretrained_text_width: int | None = None,
    ) -> None:
        """`text_encoder`: the CLIP text encoder, or None when a pretrained text encoder's states of width
        `pretrained_text_width` condition the UNet instead (they come with each call, see `encode_text`)."""
        super().__init__()
        if (text_encoder is None) == (pretrained_text_width is None):
            raise ValueError("System 3 needs either its CLIP text encoder or the width of a pretrained text "
                             "encoder's states (TriVLAConfig.text_encoder), not both")
        self.config = config
        self.tokenizer = tokenizer
        self.vae = vae
        self.text_encoder = text_encoder
        self.unet = unet
        text_width = text_encoder.config.hidden_size if text_encoder is not None else pretrained_text_width
        # Text width -> UNet cross-attention width (SVD's UNet expects its image-embedding width).
        self.text_projection = nn.Linear(text_width, unet.config.cross_attention_dim)
        n_up = len(unet.up_blocks)
        if not 1 <= config.feature_up_blocks <= n_up:
            raise ValueError(f"dynamics.feature_up_blocks must be in [1, {n_up}]; got {config.feature_up_blocks}")
        if unet.config.in_channels != 2 * vae.config.latent_channels:
            raise ValueError(
                f"the UNet takes {unet.config.in_channels} channels; noise + condition latents give "
                f"{2 * vae.config.latent_channels}"
            )
        if text_encoder is not None and config.text_max_tokens > text_encoder.config.max_position_embeddings:
            raise ValueError(
                f"dynamics.text_max_tokens ({config.text_max_tokens}) exceeds the text encoder's "
                f"{text_encoder.config.max_position_embeddings} positions"
            )
        if text_encoder is not None and tokenizer.vocab_size > text_encoder.config.vocab_size:
            raise ValueError(
                f"the text tokenizer has {tokenizer.vocab_size} ids but the text encoder only "
                f"{text_encoder.config.vocab_size} (dynamics.text.vocab_size)"
            )
        self.latent_downsample = 2 ** (len(vae.config.block_out_channels) - 1)
        if config.video_size % self.latent_downsample:
            raise ValueError(
                f"dynamics.video_size ({config.video_size}) must be a multiple of the VAE's downsampling "
                f"{self.latent_downsample}"
            )
        # The "fixed" noise latents of the one-pass features, drawn once (see DynamicsConfig.feature_noise).
        side = config.video_size // self.latent_downsample
        fixed = torch.Generator().manual_seed(config.feature_noise_seed)
        self.register_buffer(
            "fixed_feature_noise",
            # drawn on the CPU (where `fixed` lives), then moved to the device the model is being built on
            torch.randn((1, config.num_frames, vae.config.latent_channels, side, side), generator=fixed,
                        device="cpu").to(torch.get_default_device()),
            persistent=False,
        )

    @classmethod
    def from_config(
        cls,
        config: DynamicsConfig,
        tokenizer: TextTokenizer,
        *,
        component_configs: dict | None = None,
        load_pretrained: bool = True,
        pretrained_text_width: int | None = None,
    ) -> "DynamicsPerceptionModule":
        """Builds the module from recorded component configs, local pretrained directories named in
        `config` (SVD's unet/ and vae/, a CLIP text encoder), or randomly initialised from its shapes.
        With `pretrained_text_width` (a pretrained text encoder's, see `__init__`) no CLIP is built."""
        if component_configs is not None:
            vae = pretrained.build_svd_vae(component_configs["vae"])
            unet = pretrained.build_svd_unet(component_configs["unet"])
            text = None if pretrained_text_width is not None else pretrained.build_clip_text(component_configs["text"])
            return cls(config, tokenizer, vae, text, unet, pretrained_text_width)
        unet_path = config.unet_path or config.svd_path
        vae_path = config.vae_path or config.svd_path
        if load_pretrained and vae_path:
            vae = pretrained.load_svd_vae(vae_path)
        else:
            vae = pretrained.build_svd_vae(pretrained.svd_vae_config(config.vae))
        if load_pretrained and unet_path:
            unet = pretrained.load_svd_unet(unet_path)
        else:
            unet = pretrained.build_svd_unet(
                pretrained.svd_unet_config(
                    config.unet, latent_channels=vae.config.latent_channels, num_frames=config.num_frames
                )
            )
        if pretrained_text_width is not None:
            text = None
        elif load_pretrained and config.text_encoder_path:
            text = pretrained.load_clip_text(config.text_encoder_path)
        else:
            bos = tokenizer.bos_token_id if tokenizer.bos_token_id is not None else tokenizer.pad_token_id
            eos = tokenizer.eos_token_id if tokenizer.eos_token_id is not None else tokenizer.pad_token_id
            text = pretrained.build_clip_text(
                pretrained.clip_text_config(
                    config.text, pad_token_id=tokenizer.pad_token_id, bos_token_id=bos, eos_token_id=eos
                )
            )
        return cls(config, tokenizer, vae, text, unet, pretrained_text_width)

    def component_configs(self) -> dict:
        """Library configs of the parts, enough to rebuild this architecture without the original files (no
        "text" when a pretrained text encoder, kept out of checkpoints, stands for CLIP)."""
        configs = {
            "vae": pretrained.component_config_dict(self.vae),
            "unet": pretrained.component_config_dict(self.unet),
        }
        if self.text_encoder is not None:
            configs["text"] = pretrained.component_config_dict(self.text_encoder)
        return configs

    # ------------------------------------------------------------------ shapes

    @property
    def num_frames(self) -> int:
        """Clip length T+1 (the current frame and the predicted future)."""
        return self.config.num_frames

    @property
    def feature_up_block_channels(self) -> list[int]:
        """C_m of each up-block read out (eq. 2)."""
        reversed_channels = list(reversed(self.unet.config.block_out_channels))
        return reversed_channels[: self.config.feature_up_blocks]

    @property
    def feature_channels(self) -> int:
        """sum_m C_m, the channels of F_p."""
        return sum(self.feature_up_block_channels)

    @property
    def feature_shape(self) -> tuple[int, int, int, int]:
        """Shape of one view's F_p: (T+1, sum C_m, H_p, W_p)."""
        s = self.config.feature_size
        return (self.num_frames, self.feature_channels, s, s)

    @property
    def latent_size(self) -> int:
        """Side of the VAE latents."""
        return self.config.video_size // self.latent_downsample

    # ------------------------------------------------------------------ conditioning

    def text_token_ids(self, instruction_ids: list[list[int]]) -> torch.Tensor:
        """[BOS] ids [EOS] padded to `text_max_tokens`, as CLIP is used in SD/SVD: (B, text_max_tokens)."""
        tok = self.tokenizer
        length = self.config.text_max_tokens
        out = torch.full((len(instruction_ids), length), tok.pad_token_id, dtype=torch.long)
        for b, ids in enumerate(instruction_ids):
            seq = ([tok.bos_token_id] if tok.bos_token_id is not None else []) + list(ids)
            seq = seq[: length - 1] + ([tok.eos_token_id] if tok.eos_token_id is not None else [])
            out[b, : len(seq)] = torch.tensor(seq, dtype=torch.long)
        return out

    def text_hidden(self, text: list[list[int]] | torch.Tensor) -> torch.Tensor:
        """The unprojected text conditioning (B, N, width): CLIP's hidden states of instruction token ids, or,
        without CLIP, a pretrained text encoder's conditioning (B, text_max_tokens, width) as given
        (`text_encoder.sentence_then_tokens`)."""
        device = self.text_projection.weight.device
        if self.text_encoder is not None:
            if torch.is_tensor(text):
                raise ValueError("this System 3 reads instruction token ids with its CLIP text encoder, not a "
                                 "pretrained text encoder's states")
            return self.text_encoder(input_ids=self.text_token_ids(text).to(device)).last_hidden_state
        width = self.text_projection.in_features
        if not torch.is_tensor(text) or text.dim() != 3 or tuple(text.shape[1:]) != (self.config.text_max_tokens, width):
            got = tuple(text.shape) if torch.is_tensor(text) else type(text).__name__
            raise ValueError(f"this System 3 reads a pretrained text encoder's conditioning (B, "
                             f"{self.config.text_max_tokens}, {width}) (TriVLAConfig.text_encoder); got {got}")
        return text.to(device, self._dtype)

    def encode_text(self, text: list[list[int]] | torch.Tensor) -> torch.Tensor:
        """The text conditioning (`text_hidden`) projected to the UNet's cross-attention width."""
        return self.text_projection(self.text_hidden(text))

    def encode_frames(self, frames: torch.Tensor) -> "object":
        """VAE posterior (diffusers DiagonalGaussianDistribution) of uint8 frames (N, H, W, 3)."""
        x = frames_to_vae_input(frames.to(self.text_projection.weight.device), self.config.video_size, self._dtype)
        return self.vae.encode(x).latent_dist

    def added_time_ids(self, batch: int) -> torch.Tensor:
        """SVD's micro-conditioning (fps - 1, motion bucket, noise augmentation), (B, 3)."""
        c = self.config
        row = torch.tensor([c.fps_id, c.motion_bucket_id, c.noise_aug_strength], dtype=self._dtype)
        return row.expand(batch, 3).to(self.text_projection.weight.device)

    @property
    def _dtype(self) -> torch.dtype:
        return self.text_projection.weight.dtype

    def _unet_input(self, noisy_scaled: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        """Noise latents (B, T, C, h, w) with the current frame's latent repeated over T on channels."""
        frames = noisy_scaled.shape[1]
        return torch.cat([noisy_scaled, condition.unsqueeze(1).expand(-1, frames, -1, -1, -1)], dim=2)

    # ------------------------------------------------------------------ inference: eq. (2)-(3)

    def forward(
        self, frames: torch.Tensor, instruction_ids: list[list[int]] | torch.Tensor, *,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """One-pass predictive features F_p (B, T+1, sum C_m, H_p, W_p) of current frames uint8 (B, H, W, 3) and
        their instructions (token ids, or a pretrained text encoder's conditioning: `text_hidden`).
        `generator` draws the noise latents only with `feature_noise="random"`."""
        batch = frames.shape[0]
        device = self.text_projection.weight.device
        condition = self.encode_frames(frames).mode()  # SVD conditions on the unscaled latent mode
        text = self.encode_text(instruction_ids)
        sigma = torch.full((batch,), self.config.sigma_max, dtype=torch.float32)
        shape = (batch, self.num_frames, condition.shape[1], condition.shape[2], condition.shape[3])
        eps = self._feature_noise(shape, generator)
        noisy = (noise_schedule.c_in(sigma) * sigma).view(-1, 1, 1, 1, 1) * eps  # c_in * (x_0 ~ 0 + sigma eps)
        sample = self._unet_input(noisy.to(device, self._dtype), condition)
        timestep = noise_schedule.c_noise(sigma).to(device, self._dtype)
        ups = self.unet.up_blocks[: self.config.feature_up_blocks]
        outputs = run_until(
            lambda: self.unet(sample, timestep, text, self.added_time_ids(batch), return_dict=False),
            list(ups),
            ups[-1],
        )
        size = self.config.feature_size
        resized = [
            F.interpolate(out, size=(size, size), mode="bilinear", align_corners=False) for out in outputs
        ]  # each (B*(T+1), C_m, H_p, W_p)
        features = torch.cat(resized, dim=1)
        return features.unflatten(0, (batch, self.num_frames))

    def _feature_noise(self, shape: tuple[int, ...], generator: torch.Generator | None) -> torch.Tensor:
        """Unit Gaussian noise latents (B, T, C, h, w) of the one-pass features (see `feature_noise`)."""
        if self.config.feature_noise == "random":
            return torch.randn(shape, generator=generator, dtype=torch.float32)
        return self.fixed_feature_noise.float().cpu().expand(shape)

    @torch.no_grad()
    def predict_clip(
        self, frames: torch.Tensor, instruction_ids: list[list[int]] | torch.Tensor, *,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """The one-step clip prediction (the paper's Fig. 5): the full UNet at the final noise level
        from pure-noise latents, denoised and decoded. uint8 (B, H, W, 3) -> uint8 (B, T+1, S, S, 3),
        S = video_size. For inspection only; the policy uses `forward`'s features."""
        batch = frames.shape[0]
        device = self.text_projection.weight.device
        condition = self.encode_frames(frames).mode()
        text = self.encode_text(instruction_ids)
        sigma = torch.full((batch,), self.config.sigma_max, dtype=torch.float32)
        shape = (batch, self.num_frames, condition.shape[1], condition.shape[2], condition.shape[3])
        eps = torch.randn(shape, generator=generator, dtype=torch.float32).to(device, self._dtype)
        s = sigma.view(-1, 1, 1, 1, 1).to(device, self._dtype)
        noisy = s * eps
        sample = self._unet_input(noise_schedule.c_in(s) * noisy, condition)
        out = self.unet(sample, noise_schedule.c_noise(sigma).to(device, self._dtype), text,
                        self.added_time_ids(batch), return_dict=False)[0]
        denoised = noise_schedule.c_skip(s) * noisy + noise_schedule.c_out(s) * out
        latents = denoised.flatten(0, 1) / self.vae.config.scaling_factor
        decoded = self._decode(latents)
        pixels = ((decoded.float().clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8)
        return pixels.permute(0, 2, 3, 1).unflatten(0, (batch, self.num_frames))

    def _decode(self, latents: torch.Tensor) -> torch.Tensor:
        try:  # SVD's temporal decoder wants the clip length
            return self.vae.decode(latents, num_frames=self.num_frames).sample
        except TypeError:
            return self.vae.decode(latents).sample

    # ------------------------------------------------------------------ training: eq. (1)

    def video_loss(
        self,
        video: torch.Tensor,
        instruction_ids: list[list[int]] | torch.Tensor,
        *,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Eq. (1): || D(x_sigma; l_emb, s_0) - x_0 ||^2 for clips uint8 (B, T+1, H, W, 3) whose frame 0 is
        the current frame (instructions as in `forward`). The VAE and CLIP (or the pretrained text encoder) stay
        frozen (no gradient); the UNet and text projection learn."""
        batch, frames = video.shape[:2]
        if frames != self.num_frames:
            raise ValueError(f"batch['video'] must have {self.num_frames} frames (dynamics.num_frames); got {frames}")
        device = self.text_projection.weight.device
        with torch.no_grad():
            posterior = self.encode_frames(video.flatten(0, 1))
            x0 = posterior.sample(generator=generator) * self.vae.config.scaling_factor
            x0 = x0.unflatten(0, (batch, frames))
            condition = posterior.mode().unflatten(0, (batch, frames))[:, 0]
            text_hidden = self.text_hidden(instruction_ids)
        text = self.text_projection(text_hidden)
        c = self.config
        sigma = noise_schedule.sample_training_sigmas(
            batch,
            c.train_log_sigma_mean,
            c.train_log_sigma_std,
            sigma_min=c.sigma_min,
            sigma_max=c.sigma_max,
            generator=generator,
        ).to(device, self._dtype)
        eps = torch.randn(x0.shape, generator=generator, dtype=torch.float32).to(device, self._dtype)
        s = sigma.view(-1, 1, 1, 1, 1)
        noisy = x0 + s * eps
        sample = self._unet_input(noise_schedule.c_in(s) * noisy, condition)
        out = self.unet(sample, noise_schedule.c_noise(sigma), text, self.added_time_ids(batch), return_dict=False)[0]
        denoised = noise_schedule.c_skip(s) * noisy + noise_schedule.c_out(s) * out
        loss = F.mse_loss(denoised.float(), x0.float())
        return loss, {"video_loss": float(loss.detach()), "sigma_mean": float(sigma.mean())}
