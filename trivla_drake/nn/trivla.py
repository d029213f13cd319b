"""The whole TriVLA model: System 2 (vision-language), System 3 (dynamics perception), System 1 (policy).

Two interfaces:
- per observation, numpy in / numpy out, split so that Drake systems can run the parts at different
  rates: `encode_vision_language`, `encode_dynamics`, `sample_actions`, composed by `predict_action_chunk`;
- batched torch tensors for training: the losses of the three systems, in trivla_losses.py (a mixin of this
  class, so they are `model.compute_loss(...)` etc.).
Actions leave the model unnormalised; the model applies the normalisation statistics it carries.

A pretrained text encoder (`config.text_encoder`, nn/text_encoder.py) is held outside the registered modules: it
is frozen, never saved in checkpoints nor moved with the model, and reads each instruction once (its cache).
"""

from __future__ import annotations

import contextlib

from typing import Any, Mapping

import numpy as np
import torch
from torch import nn

from trivla_drake.nn.chat_prompt import check_instruction_text, tokenize_instruction
from trivla_drake.nn.config import TriVLAConfig, text_encoder_feeds, validate_config
from trivla_drake.nn.dynamics import DynamicsPerceptionModule
from trivla_drake.nn.embodiment import check_embodiment_ids
from trivla_drake.nn.panda_gripper import gripper_closure
from trivla_drake.nn.panda_tcp import PandaTcpFeatures, denormalize_position
from trivla_drake.nn.normalization import NormalizationStats, Normalizer
from trivla_drake.nn.observation import check_embodiment_id, check_image, check_observation, check_state
from trivla_drake.nn.policy import FlowMatchingPolicy, check_noise_scale
from trivla_drake.nn.text_encoder import PretrainedTextEncoder, load_text_encoder, sentence_then_tokens
from trivla_drake.nn.shared_instruction import shared_instruction
from trivla_drake.nn.tokenizer import TextTokenizer, load_tokenizer
from trivla_drake.nn.trivla_losses import TriVLATrainingLosses
from trivla_drake.nn.vision_language import VisionLanguageModule

# Independent random streams derived from one user seed.
_DYNAMICS_STREAM = 1
_ACTION_STREAM = 2


def resolve_seed(seed: int | None) -> int:
    """`seed` itself, or a fresh one drawn from torch's global generator when None."""
    if seed is None:
        return int(torch.randint(0, 2**62, (1,)))
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an int or None; got {seed!r}")
    return int(seed)


def stream_generator(seed: int, stream: int) -> torch.Generator:
    """A CPU generator for one random stream (dynamics noise, action noise) of a seed."""
    return torch.Generator().manual_seed((int(seed) * 1_000_003 + stream) % (2**63 - 1))


def _cuda_devices() -> list[int]:
    """The CUDA devices whose generators a seeded initialisation forks (none without CUDA)."""
    return list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []


class TriVLA(TriVLATrainingLosses, nn.Module):
    """TriVLA: System 2 gives Q_vl, System 3 gives F_p per view, System 1 turns Q_vl, Q_p and Q_s into a
    (10, 7) action chunk by flow matching. `config.use_system2/3 = False` drops a system (Table 4)."""

    def __init__(
        self,
        config: TriVLAConfig,
        *,
        normalization: NormalizationStats | None = None,
        component_configs: dict[str, Any] | None = None,
        tokenizers: dict[str, TextTokenizer] | None = None,
        load_pretrained: bool = True,
        text_encoder: PretrainedTextEncoder | None = None,
    ) -> None:
        """Builds the model. Weights come from the local pretrained directories named in `config` when
        `load_pretrained`; everything else is initialised from `config.init_seed` (the global RNG is left
        untouched). `component_configs` / `tokenizers` are what `load_checkpoint` passes to rebuild exactly.
        The pretrained text encoder `config.text_encoder` (when a system reads it) is `text_encoder` if given,
        else loaded from its spec, whatever `load_pretrained` says: it has no random variant."""
        super().__init__()
        validate_config(config)
        self.config = config
        tokenizers = tokenizers or {}
        components = component_configs or {}
        if text_encoder_feeds(config, 2) or text_encoder_feeds(config, 3):
            text_encoder = text_encoder or load_text_encoder(config.text_encoder)
        else:
            text_encoder = None
        # Not registered as a submodule: its weights stay out of state_dict(), checkpoints and .to().
        object.__setattr__(self, "text_encoder", text_encoder)
        with torch.random.fork_rng(devices=_cuda_devices()):  # seeded initialisation, global RNGs restored
            torch.manual_seed(config.init_seed)
            self.vision_language: VisionLanguageModule | None = None
            self.dynamics: DynamicsPerceptionModule | None = None
            if config.use_system2:
                vl = config.vision_language
                tok = tokenizers.get("vision_language") or load_tokenizer(
                    vl.tokenizer_path if load_pretrained else None
                )
                self.vision_language = VisionLanguageModule.from_config(
                    vl, tok, component_configs=components.get("vision_language"), load_pretrained=load_pretrained,
                    instruction_width=text_encoder.width if text_encoder_feeds(config, 2) else None,
                )
            if config.use_system3:
                dyn = config.dynamics
                tok = tokenizers.get("dynamics") or load_tokenizer(dyn.text_tokenizer_path if load_pretrained else None)
                self.dynamics = DynamicsPerceptionModule.from_config(
                    dyn, tok, component_configs=components.get("dynamics"), load_pretrained=load_pretrained,
                    pretrained_text_width=text_encoder.width if text_encoder_feeds(config, 3) else None,
                )
            self.policy = self._new_policy()
        pol = config.policy
        stats = normalization or NormalizationStats.identity(pol.state_dim, pol.action_dim)
        stats.check_dims(pol.state_dim, pol.action_dim)
        self.normalizer = Normalizer(stats)
        self.tcp_features = PandaTcpFeatures() if pol.tcp_features else None
        self.image_size = (
            self.vision_language.image_size if self.vision_language else config.vision_language.vision.image_size
        )

    def _new_policy(self) -> FlowMatchingPolicy:
        """A System 1 for this model's config and Systems 2 / 3, drawn from torch's global generator."""
        return FlowMatchingPolicy(
            self.config.policy,
            vl_dim=self.vision_language.hidden_size if self.vision_language else None,
            dynamics_feature_shape=self.dynamics.feature_shape if self.dynamics else None,
            vl_fixed_positions=self.vision_language.instruction_offset(2) if self.vision_language else 0,
        )

    def reset_system1(self, seed: int, keep_binding: bool = False) -> None:
        """Replaces System 1 by a fresh one initialised from `seed` (the global RNGs are left untouched),
        keeping Systems 2 and 3: System 1 trained from scratch on pretrained Systems 2 / 3. With
        `keep_binding` the new System 1 takes the old one's `binding_parameters` (its instruction grounding
        but the goal projection, and the Q_vl path that grounding reads) and its buffers (the feature
        statistics that binding was learnt on), so only the rest is fresh."""
        old_policy = self.policy
        kept = {}
        if keep_binding:
            kept = {**old_policy.binding_parameters(), **dict(old_policy.named_buffers())}
        old = next(old_policy.parameters())
        with torch.random.fork_rng(devices=_cuda_devices()):
            torch.manual_seed(seed)
            self.policy = self._new_policy().to(old.device, old.dtype)
        if kept:
            fresh = {**self.policy.binding_parameters(), **dict(self.policy.named_buffers())}
            with torch.no_grad():
                for name, value in kept.items():
                    fresh[name].copy_(value)

    # ------------------------------------------------------------------ bookkeeping

    @property
    def device(self) -> torch.device:
        """Device of the weights."""
        return self.policy.action_pos.device

    @property
    def normalization(self) -> NormalizationStats:
        """The normalisation statistics applied to states and actions."""
        return self.normalizer.stats

    def set_normalization(self, stats: NormalizationStats) -> None:
        """Replaces the normalisation statistics (e.g. with those of the training set)."""
        stats.check_dims(self.config.policy.state_dim, self.config.policy.action_dim)
        self.normalizer.set_stats(stats)

    @property
    def initial_noise_scale(self) -> float:
        """Standard deviation of the noise System 1's sampling starts from (1: the paper's)."""
        return self.policy.initial_noise_scale

    def set_initial_noise_scale(self, scale: float) -> None:
        """Sets the standard deviation of the noise System 1's sampling starts from (see
        `FlowMatchingPolicy.initial_noise_scale`; not saved in checkpoints); ValueError unless it is a
        finite number >= 0."""
        self.policy.initial_noise_scale = check_noise_scale(scale)

    def parameter_counts(self) -> dict[str, int]:
        """Parameters per system: system2 (SigLIP, projector, LLM), system3 (VAE, CLIP text, UNet),
        system1 (state encoder, Video Former, DiT, action encoder/decoder); with a pretrained text encoder
        (`config.text_encoder`), text_encoder: its frozen parameters, which run at inference but are not in the
        checkpoint; and total, all of them."""

        def count(module: nn.Module | None) -> int:
            return sum(p.numel() for p in module.parameters()) if module is not None else 0

        counts = {
            "system2": count(self.vision_language),
            "system3": count(self.dynamics),
            "system1": count(self.policy),
        }
        if self.text_encoder is not None:
            counts["text_encoder"] = count(self.text_encoder)
        counts["total"] = sum(counts.values())
        return counts

    def component_configs(self) -> dict[str, Any]:
        """Library configs of the pretrained-architecture parts (recorded in checkpoints)."""
        out: dict[str, Any] = {}
        if self.vision_language is not None:
            out["vision_language"] = self.vision_language.component_configs()
        if self.dynamics is not None:
            out["dynamics"] = self.dynamics.component_configs()
        return out

    def action_space(self) -> dict[str, Any]:
        """Description of the action chunk the model outputs."""
        pol = self.config.policy
        return {
            "horizon": pol.action_horizon,
            "dim": pol.action_dim,
            "names": list(self.config.action_names),
            "description": "relative end-effector pose change (dx, dy, dz, drx, dry, drz) and gripper command, "
            "unnormalised, one row per control step",
        }

    # ------------------------------------------------------------------ tokenisation

    def _encoder_texts(self, instructions: list[str], field: str, max_tokens: int, limit: str) -> list[str]:
        """The instructions for the pretrained text encoder, stripped; ValueError naming `field` unless each is a
        non-empty str of at most `max_tokens` of its tokens ([CLS] and [SEP] included; `limit` names the bound)."""
        texts = []
        for instruction in instructions:
            text = check_instruction_text(instruction, field)
            count = self.text_encoder.token_count(text)
            if count > max_tokens:
                raise ValueError(f"{field} is too long: {count} text encoder tokens, at most {max_tokens} are "
                                 f"accepted ({limit})")
            texts.append(text)
        return texts

    def _vl_inputs(
        self, instructions: list[str], field: str
    ) -> tuple[list[list[int]], tuple[torch.Tensor, torch.Tensor] | None]:
        """System 2's instruction inputs: token ids and None, or, when the pretrained text encoder feeds System 2,
        placeholder ids and its (token states, mask) on the model's device."""
        if self.vision_language.instruction_projection is None:
            return self._vl_instruction_ids(instructions, field), None
        max_tokens = self.config.vision_language.max_instruction_tokens
        encoded = self.text_encoder.encode(
            self._encoder_texts(instructions, field, max_tokens, "vision_language.max_instruction_tokens"))
        mask = encoded.mask.to(self.device)
        return self.vision_language.instruction_placeholders(mask), (encoded.token_states.to(self.device), mask)

    def _vl_instruction_ids(self, instructions: list[str], field: str) -> list[list[int]]:
        """System 2's instruction token ids (placeholders when the pretrained text encoder feeds it)."""
        vl = self.vision_language
        if vl.instruction_projection is not None:
            return self._vl_inputs(instructions, field)[0]
        return [
            tokenize_instruction(vl.tokenizer, text, self.config.vision_language.max_instruction_tokens, field)
            for text in instructions
        ]

    def _dyn_instruction_ids(self, instructions: list[str], field: str) -> list[list[int]] | torch.Tensor:
        """System 3's instructions: CLIP token ids, or, when the pretrained text encoder feeds System 3, its
        conditioning (B, text_max_tokens, width) (`text_encoder.sentence_then_tokens`) on the model's device."""
        dyn = self.dynamics
        length = self.config.dynamics.text_max_tokens
        if dyn.text_encoder is None:
            texts = self._encoder_texts(instructions, field, length - 1, "dynamics.text_max_tokens, less one for "
                                        "the sentence embedding")
            return sentence_then_tokens(self.text_encoder.encode(texts), length).to(self.device)
        specials = (dyn.tokenizer.bos_token_id is not None) + (dyn.tokenizer.eos_token_id is not None)
        return [
            tokenize_instruction(dyn.tokenizer, text, length - specials, field)
            for text in instructions
        ]

    def check_instruction(self, instruction: Any, field: str = "instruction") -> None:
        """Raises ValueError naming `field` if an instruction is not a non-empty, short-enough str."""
        if self.vision_language is not None:
            if self.vision_language.instruction_projection is not None:
                self._encoder_texts([instruction], field, self.config.vision_language.max_instruction_tokens,
                                    "vision_language.max_instruction_tokens")
            else:
                self._vl_instruction_ids([instruction], field)
        if self.dynamics is not None:
            if self.dynamics.text_encoder is None:
                self._encoder_texts([instruction], field, self.config.dynamics.text_max_tokens - 1,
                                    "dynamics.text_max_tokens, less one for the sentence embedding")
            else:
                self._dyn_instruction_ids([instruction], field)
        if self.vision_language is None and self.dynamics is None:
            tokenize_instruction(load_tokenizer(None), instruction, 10**9, field)

    # ------------------------------------------------------------------ batched torch API

    def _images(self, images: Any, name: str) -> torch.Tensor:
        t = torch.as_tensor(images)
        size = self.image_size
        if t.dtype != torch.uint8 or t.dim() != 4 or tuple(t.shape[1:]) != (size, size, 3):
            raise ValueError(f"{name} must be uint8 (B, {size}, {size}, 3); got {t.dtype} {tuple(t.shape)}")
        return t.to(self.device)

    def encode_vision_language_batch(
        self, static_rgb: torch.Tensor, wrist_rgb: torch.Tensor, instructions: list[str]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """System 2 on a batch: uint8 (B, H, W, 3) views and B instructions -> Q_vl (B, S, D_llm), mask (B, S)."""
        if self.vision_language is None:
            raise ValueError("System 2 is disabled in this model (config.use_system2 = False)")
        images = torch.stack([self._images(static_rgb, "static_rgb"), self._images(wrist_rgb, "wrist_rgb")], dim=1)
        ids, states = self._vl_inputs(list(instructions), "instruction")
        return self.vision_language(images, ids, states)

    def encode_state_batch(self, state: torch.Tensor, embodiment_id: torch.Tensor) -> torch.Tensor:
        """Unnormalised states (B, state_dim) -> Q_s (B, hidden) with each sample's embodiment MLP."""
        state = torch.as_tensor(state, dtype=torch.float32, device=self.device)
        embodiment_id = torch.as_tensor(embodiment_id, device=self.device)
        check_embodiment_ids(embodiment_id, self.config.policy.num_embodiments)
        if not torch.isfinite(state).all():
            raise ValueError("state has NaN or infinite entries")
        return self.policy.encode_state(self._state_input(state), embodiment_id)

    def _state_input(self, state: torch.Tensor) -> torch.Tensor:
        """System 1's state input: the normalised state, then the tcp features if configured."""
        normalised = self.normalizer.normalize_state(state)
        if self.tcp_features is None:
            return normalised
        return torch.cat([normalised, self.tcp_features(state).to(normalised.dtype)], dim=-1)

    def encode_dynamics_batch(
        self,
        static_rgb: torch.Tensor,
        wrist_rgb: torch.Tensor,
        instructions: list[str],
        *,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """System 3 on a batch, both views in ONE UNet pass -> F_p^static, F_p^wrist, each (B, T+1, C, H_p, W_p)."""
        if self.dynamics is None:
            raise ValueError("System 3 is disabled in this model (config.use_system3 = False)")
        static = self._images(static_rgb, "static_rgb")
        wrist = self._images(wrist_rgb, "wrist_rgb")
        text = self._dyn_instruction_ids(list(instructions), "instruction")
        both = torch.cat([text, text]) if torch.is_tensor(text) else text + text
        # One instruction without gradients (a policy call, the feature cache): its work once, not per frame and view
        # (nn/shared_instruction.py; the same numbers). Training batches of mixed instructions take the plain path.
        once = not torch.is_grad_enabled() and len(set(instructions)) == 1
        with shared_instruction(self.dynamics) if once else contextlib.nullcontext():
            features = self.dynamics(torch.cat([static, wrist]), both, generator=generator)
        return features[: static.shape[0]], features[static.shape[0] :]

    def _conditions(self, q_s, q_vl, q_vl_mask, f_static, f_wrist, state=None):
        """System 1's conditions (FlowMatchingPolicy.conditions): Q_s with the grounding's goal, memory,
        memory mask, predicted sub-goal or None. `state` (B, state_dim), unnormalised, is read only
        with policy.subgoal_offset (the tcp features) or policy.grounding_reads_gripper (the gripper's
        closure); ValueError when such a model gets none."""
        q_p = self.policy.aggregate_dynamics(f_static, f_wrist) if self.dynamics is not None else None
        return self.policy.conditions(q_s, q_vl if self.vision_language is not None else None, q_vl_mask, q_p,
                                      self._tcp_for_policy(state, q_s.dtype), self._gripper_for_grounding(state))

    def _gripper_for_grounding(self, state: torch.Tensor | None) -> torch.Tensor | None:
        """The gripper's closure (B, 1) of unnormalised states when System 1's grounding reads it
        (policy.grounding_reads_gripper), else None."""
        if not (self.config.policy.grounding_reads_gripper and self.policy.grounding is not None):
            return None
        if state is None:
            raise ValueError("state is required: this model's instruction grounding reads the gripper's closure "
                             "(policy.grounding_reads_gripper), which it computes from the robot state")
        return gripper_closure(torch.as_tensor(state, device=self.device)).float()

    def _tcp_for_policy(self, state: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor | None:
        """The tcp features (B, 9) of unnormalised states when System 1 reads them beyond Q_s
        (policy.subgoal_offset), else None."""
        if not self.policy.reads_tcp:
            return None
        if state is None:
            raise ValueError("state is required: this System 1 reads the tool-centre point beside Q_s "
                             "(policy.subgoal_offset), which it computes from the robot state Q_s was encoded from")
        return self.tcp_features(state).to(dtype)

    def sample_actions_batch(
        self,
        q_vl: torch.Tensor | None,
        q_vl_mask: torch.Tensor | None,
        q_s: torch.Tensor,
        f_static: torch.Tensor | None,
        f_wrist: torch.Tensor | None,
        embodiment_id: torch.Tensor,
        *,
        generator: torch.Generator | None = None,
        num_steps: int | None = None,
        state: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """System 1 on a batch: Video Former once, then Euler flow-matching steps -> unnormalised (B, H, A).
        `state` (B, state_dim), unnormalised: needed only with policy.subgoal_offset (or another option
        that reads the gripper: grounding_reads_gripper)."""
        embodiment_id = torch.as_tensor(embodiment_id, device=self.device)
        check_embodiment_ids(embodiment_id, self.config.policy.num_embodiments)
        q_s, memory, mask, _ = self._conditions(q_s, q_vl, q_vl_mask, f_static, f_wrist, state)
        actions = self.policy.sample(q_s, memory, mask, embodiment_id, generator=generator, num_steps=num_steps)
        return self.normalizer.unnormalize_action(actions)

    # ------------------------------------------------------------------ per-observation numpy API

    @torch.inference_mode()
    def encode_vision_language(
        self, static_rgb: np.ndarray, wrist_rgb: np.ndarray, instruction: str, state: np.ndarray, embodiment_id: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """System 2 (and the state token). numpy uint8 (H, W, 3) views, str, float (state_dim,) ->
        Q_vl float32 (S, D_llm) (shape (0, 0) when System 2 is disabled) and Q_s float32 (hidden,)."""
        q_s = self.encode_state(state, embodiment_id)
        size = self.image_size
        static = check_image("static_rgb", static_rgb, size)
        wrist = check_image("wrist_rgb", wrist_rgb, size)
        if self.vision_language is None:
            self.check_instruction(instruction)
            return np.zeros((0, 0), dtype=np.float32), q_s
        q_vl, _ = self.encode_vision_language_batch(
            torch.from_numpy(static)[None], torch.from_numpy(wrist)[None], [instruction]
        )
        return q_vl[0].float().cpu().numpy(), q_s

    @torch.inference_mode()
    def predict_subgoal(
        self, static_rgb: np.ndarray, wrist_rgb: np.ndarray, instruction: str, state: np.ndarray | None = None
    ) -> np.ndarray:
        """Where System 1's instruction grounding puts the next gripper event: float64 (3,), the
        tool-centre-point position [m] in the arm's base frame (ValueError without a grounding).
        `state` (state_dim,), the unnormalised robot state: required when the grounding reads the gripper
        (policy.grounding_reads_gripper)."""
        if self.policy.grounding is None:
            raise ValueError("this model has no instruction grounding (policy.instruction_grounding is off)")
        pol = self.config.policy
        if state is None and pol.grounding_reads_gripper:
            raise ValueError("state is required: this model's grounding reads the gripper's closure "
                             "(policy.grounding_reads_gripper)")
        state = check_state("state", np.zeros(pol.state_dim) if state is None else state, pol.state_dim)
        q_vl, _ = self.encode_vision_language(static_rgb, wrist_rgb, instruction, state)
        subgoal = self.subgoal_of_features(torch.as_tensor(q_vl, dtype=torch.float32, device=self.device)[None], None,
                                           torch.from_numpy(state)[None].to(self.device))
        return denormalize_position(subgoal[0].double().cpu()).numpy()

    @torch.inference_mode()
    def encode_state(self, state: np.ndarray, embodiment_id: int = 0) -> np.ndarray:
        """Q_s float32 (hidden,) of an unnormalised state (state_dim,) with the embodiment's state MLP."""
        state = check_state("state", state, self.config.policy.state_dim)
        eid = check_embodiment_id("embodiment_id", embodiment_id, self.config.policy.num_embodiments)
        q_s = self.encode_state_batch(torch.from_numpy(state)[None], torch.tensor([eid]))
        return q_s[0].float().cpu().numpy()

    @torch.inference_mode()
    def encode_dynamics(
        self, static_rgb: np.ndarray, wrist_rgb: np.ndarray, instruction: str, *, seed: int | None = None
    ) -> dict[str, np.ndarray]:
        """System 3, one UNet pass for both views. Returns {"static": F_p, "wrist": F_p}, each float32
        (T+1, sum C_m, H_p, W_p); an empty dict when System 3 is disabled. `seed` draws the noise latents
        when dynamics.feature_noise is "random" (by default they are fixed, see DynamicsConfig)."""
        size = self.image_size
        static = check_image("static_rgb", static_rgb, size)
        wrist = check_image("wrist_rgb", wrist_rgb, size)
        if self.dynamics is None:
            self.check_instruction(instruction)
            return {}
        generator = stream_generator(resolve_seed(seed), _DYNAMICS_STREAM)
        f_static, f_wrist = self.encode_dynamics_batch(
            torch.from_numpy(static)[None], torch.from_numpy(wrist)[None], [instruction], generator=generator
        )
        return {"static": f_static[0].float().cpu().numpy(), "wrist": f_wrist[0].float().cpu().numpy()}

    @torch.inference_mode()
    def predict_video(self, rgb: np.ndarray, instruction: str, *, seed: int | None = None) -> np.ndarray:
        """System 3's one-step prediction of the clip from one view (Fig. 5): uint8 (H, W, 3) ->
        uint8 (T+1, S, S, 3). ValueError without System 3."""
        if self.dynamics is None:
            raise ValueError("predict_video needs System 3 (config.use_system3 = True)")
        image = check_image("rgb", rgb, self.image_size)
        self.check_instruction(instruction)
        generator = stream_generator(resolve_seed(seed), _DYNAMICS_STREAM)
        clip = self.dynamics.predict_clip(
            torch.from_numpy(image)[None], self._dyn_instruction_ids([instruction], "instruction"), generator=generator
        )
        return clip[0].cpu().numpy()

    def _as_tensor(self, value: Any, name: str, shape: tuple[int | None, ...]) -> torch.Tensor:
        t = torch.as_tensor(np.asarray(value, dtype=np.float32) if not torch.is_tensor(value) else value)
        if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
            wanted = tuple("any" if s is None else s for s in shape)
            raise ValueError(f"{name} must have shape {wanted}; got {tuple(t.shape)}")
        if not torch.isfinite(t).all():
            raise ValueError(f"{name} has NaN or infinite entries")
        return t.to(self.device, torch.float32)

    @torch.inference_mode()
    def sample_actions(
        self,
        q_vl: np.ndarray | None,
        q_s: np.ndarray,
        dynamics_features: Mapping[str, np.ndarray] | None,
        *,
        seed: int | None = None,
        embodiment_id: int = 0,
        num_steps: int | None = None,
        state: np.ndarray | None = None,
    ) -> np.ndarray:
        """System 1: Q_vl (S, D_llm), Q_s (hidden,) and the per-view F_p of `encode_dynamics` (numpy or torch)
        -> unnormalised float32 (action_horizon, action_dim). `seed` fixes the initial noise. `state`
        (state_dim,), the unnormalised robot state Q_s was made from: required with
        policy.subgoal_offset (System 1 then reads the sub-goal from the tcp), unused otherwise."""
        pol = self.config.policy
        eid = check_embodiment_id("embodiment_id", embodiment_id, pol.num_embodiments)
        q_s_t = self._as_tensor(q_s, "q_s", (pol.hidden_size,))[None]
        state_t = None if state is None else torch.from_numpy(check_state("state", state, pol.state_dim))[None].to(self.device)
        q_vl_t = None
        if self.vision_language is not None:
            if q_vl is None:
                raise ValueError("q_vl is missing: System 2 is enabled, pass encode_vision_language's Q_vl")
            q_vl_t = self._as_tensor(q_vl, "q_vl", (None, self.vision_language.hidden_size))[None]
            if q_vl_t.shape[1] == 0:
                raise ValueError("q_vl is empty: System 2 is enabled, pass encode_vision_language's Q_vl")
        f_static = f_wrist = None
        if self.dynamics is not None:
            dynamics_features = dynamics_features or {}
            shape = self.dynamics.feature_shape
            for view in ("static", "wrist"):
                if view not in dynamics_features:
                    raise ValueError(f"dynamics_features['{view}'] is missing: System 3 is enabled")
            f_static = self._as_tensor(dynamics_features["static"], "dynamics_features['static']", shape)[None]
            f_wrist = self._as_tensor(dynamics_features["wrist"], "dynamics_features['wrist']", shape)[None]
        generator = stream_generator(resolve_seed(seed), _ACTION_STREAM)
        actions = self.sample_actions_batch(
            q_vl_t, None, q_s_t, f_static, f_wrist, torch.tensor([eid], device=self.device),
            generator=generator, num_steps=num_steps, state=state_t,
        )
        return actions[0].float().cpu().numpy()

    @torch.inference_mode()
    def predict_action_chunk(
        self, observation: Mapping[str, Any], *, seed: int | None = None, num_steps: int | None = None
    ) -> np.ndarray:
        """The whole model on one observation (see observation.py for the dict) -> unnormalised float32
        (action_horizon, action_dim). Equal to sample_actions(encode_vision_language(...),
        encode_dynamics(..., seed=seed), seed=seed) for the same seed."""
        pol = self.config.policy
        obs = check_observation(
            observation, image_size=self.image_size, state_dim=pol.state_dim, num_embodiments=pol.num_embodiments
        )
        self.check_instruction(obs["instruction"], "observation['instruction']")
        seed = resolve_seed(seed)
        q_vl, q_s = self.encode_vision_language(
            obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"], obs["embodiment_id"]
        )
        features = self.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=seed)
        return self.sample_actions(
            q_vl if self.vision_language is not None else None,
            q_s,
            features,
            seed=seed,
            embodiment_id=obs["embodiment_id"],
            num_steps=num_steps,
            state=obs["state"],
        )

    def subgoal_of_features(self, q_vl: torch.Tensor, q_vl_mask: torch.Tensor | None,
                            state: torch.Tensor | None) -> torch.Tensor:
        """The instruction grounding's raw sub-goal (B, 3) in tcp feature units of precomputed Q_vl (B, S, D_llm)
        with its mask (B, S) or None, and unnormalised robot states (B, state_dim), read when the grounding reads
        the gripper (else may be None)."""
        return self.grounding_of_features(q_vl, q_vl_mask, state)[1]

    def grounding_of_features(self, q_vl: torch.Tensor, q_vl_mask: torch.Tensor | None,
                              state: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The instruction grounding's goal token (B, D_policy), which System 1's DiT reads, and its raw sub-goal
        (as `subgoal_of_features`), from the same inputs."""
        gripper = None
        if self.config.policy.grounding_reads_gripper:
            gripper = self._gripper_for_grounding(state).to(q_vl.dtype)
        return self.policy.ground(q_vl, q_vl_mask, gripper)
