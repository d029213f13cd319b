"""System 1, the policy learning module: Q_p from the Video Former (eq. 4), the embodiment-specific
state token Q_s, and a flow-matching DiT action head with embodiment-specific action encoder and
decoder that cross-attends to Q_vl and Q_p (eq. 5, trained by flow matching, see flow_matching.py)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from trivla_drake.nn import flow_matching
from trivla_drake.nn.config import PolicyConfig
from trivla_drake.nn.dit import DiffusionTransformer, TimeEmbedding, sinusoidal_embedding
from trivla_drake.nn.embodiment import EmbodimentLinear, EmbodimentMLP
from trivla_drake.nn.panda_tcp import FEATURE_DIM as TCP_FEATURE_DIM
from trivla_drake.nn.feature_standardizer import FeatureStandardizer, SequenceStandardizer
from trivla_drake.nn.instruction_grounding import InstructionGrounding
from trivla_drake.nn.video_former import VideoFormer


def check_noise_scale(scale: float, field: str = "noise_scale") -> float:
    """`scale` as a float; ValueError naming `field` unless it is a finite number >= 0."""
    scale = float(scale)
    if not (math.isfinite(scale) and scale >= 0):
        raise ValueError(f"{field} must be a finite number >= 0, got {scale}")
    return scale


class ActionEncoder(nn.Module):
    """Embodiment-specific encoder of a noisy action chunk and its flow time into DiT tokens (GR00T's)."""

    def __init__(self, num_embodiments: int, action_dim: int, dim: int) -> None:
        super().__init__()
        self.dim = dim
        self.w1 = EmbodimentLinear(num_embodiments, action_dim, dim)
        self.w2 = EmbodimentLinear(num_embodiments, 2 * dim, dim)
        self.w3 = EmbodimentLinear(num_embodiments, dim, dim)

    def forward(self, actions: torch.Tensor, t: torch.Tensor, embodiment_id: torch.Tensor) -> torch.Tensor:
        """actions (B, H, A), t (B,) -> tokens (B, H, dim)."""
        a = self.w1(actions, embodiment_id)
        tau = sinusoidal_embedding(t, self.dim).to(a.dtype).unsqueeze(1).expand_as(a)
        return self.w3(F.silu(self.w2(torch.cat([a, tau], dim=-1), embodiment_id)), embodiment_id)


class SubgoalOffsetEncoder(nn.Module):
    """(sub-goal - tcp position) (B, 3) in tcp feature units -> a term (B, D) added to Q_s.

    The sub-goal is detached: flow matching must not move the grounding to suit the offset (the bind
    phase trains the grounding; research/instruction_grounding). The offset is multiplied by
    `OFFSET_GAIN` first, so that a centimetre (0.05 feature units) is not lost in the MLP's first
    layer; the output layer starts at zero, so a System 1 given this module starts as the one without."""

    OFFSET_GAIN = 5.0  # feature units are 0.2 m: after the gain, 1 is 4 cm

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(3, dim), nn.SiLU(), nn.Linear(dim, dim))
        nn.init.zeros_(self.mlp[2].weight)
        nn.init.zeros_(self.mlp[2].bias)

    def forward(self, subgoal: torch.Tensor, tcp_position: torch.Tensor) -> torch.Tensor:
        offset = (subgoal.detach() - tcp_position.to(subgoal.dtype)) * self.OFFSET_GAIN
        return self.mlp(offset)


class FlowMatchingPolicy(nn.Module):
    """System 1: Video Former -> Q_p; state MLP -> Q_s; DiT velocity field over action chunks."""

    def __init__(
        self,
        config: PolicyConfig,
        *,
        vl_dim: int | None,
        dynamics_feature_shape: tuple[int, int, int, int] | None,
        vl_fixed_positions: int = 0,
        vl_view_spans: tuple[tuple[int, int], ...] = (),
    ) -> None:
        """`vl_fixed_positions`: how many leading Q_vl tokens (prompt head and image tokens) are the same
        kind in every prompt, so each gets its own standardisation statistics. `vl_view_spans`: (first
        index, count) of each view's image tokens in Q_vl, static then wrist (the grounding's anchor reads them)."""
        super().__init__()
        self.config = config
        # Standard deviation of the noise sampling starts from (flow-matching "temperature"): 1 samples
        # the learned action distribution (the paper's), 0 integrates the flow from the noise mean, one
        # deterministic chunk per observation. An inference setting, not saved with the weights:
        # `TriVLA.set_initial_noise_scale`, or inference.noise_scale in `evaluate`, `demo` and `tables`.
        self.initial_noise_scale = 1.0
        dim, num_emb = config.hidden_size, config.num_embodiments
        self.state_input_dim = config.state_dim + (TCP_FEATURE_DIM if config.tcp_features else 0)
        self.state_encoder = EmbodimentMLP(num_emb, self.state_input_dim, dim, dim)
        self.action_encoder = ActionEncoder(num_emb, config.action_dim, dim)
        self.action_pos = nn.Parameter(torch.randn(config.action_horizon, dim) * 0.02)
        self.time_embed = TimeEmbedding(dim)
        self.dit = DiffusionTransformer(dim, config.num_layers, config.num_heads, config.mlp_ratio)
        self.action_decoder = EmbodimentMLP(num_emb, dim, dim, config.action_dim)
        self.source_embed = nn.Parameter(torch.randn(2, dim) * 0.02)  # marks Q_vl vs Q_p tokens
        self.uses_vl = vl_dim is not None
        self.uses_dynamics = dynamics_feature_shape is not None
        if self.uses_vl:
            self.vl_standardizer = SequenceStandardizer(vl_fixed_positions, vl_dim)
            self.vl_norm = nn.LayerNorm(vl_dim)
            self.vl_proj = nn.Linear(vl_dim, dim)
            self.vl_position = (
                nn.Parameter(torch.randn(vl_fixed_positions, dim) * 0.02)
                if config.vl_position_embedding and vl_fixed_positions > 0 else None
            )
            self.vl_fixed_positions = vl_fixed_positions
        self.vl_view_spans = tuple(vl_view_spans)
        self.grounding = None
        if config.instruction_grounding:
            if not (self.uses_vl and vl_fixed_positions > 0):
                raise ValueError("policy.instruction_grounding reads System 2's instruction and image tokens: "
                                 "it needs System 2")
            self.grounding = self._new_grounding()
        self.subgoal_offset = None
        if config.subgoal_offset:
            if self.grounding is None:
                raise ValueError("policy.subgoal_offset reads the instruction grounding's sub-goal: it needs "
                                 "policy.instruction_grounding")
            self.subgoal_offset = SubgoalOffsetEncoder(dim)
        if self.uses_dynamics:
            frames, channels, size, _ = dynamics_feature_shape
            # One set of statistics per view and feature element, shared by the T+1 frames.
            self.dynamics_standardizers = nn.ModuleList(
                [FeatureStandardizer((channels, size, size)) for _ in ("static", "wrist")]
            )
            self.video_former = VideoFormer(
                feature_channels=channels,
                num_frames=frames,
                feature_size=size,
                dim=config.former_dim,
                depth=config.former_depth,
                num_heads=config.former_heads,
                queries_per_frame=config.former_queries_per_frame,
            )
            self.dynamics_proj = nn.Linear(config.former_dim, dim)
        if not (self.uses_vl or self.uses_dynamics):
            # The System-1-only ablation: nothing to attend to but a learned token (state-only policy).
            self.null_memory = nn.Parameter(torch.randn(1, dim) * 0.02)

    # ------------------------------------------------------------------ conditions

    def encode_state(self, state: torch.Tensor, embodiment_id: torch.Tensor) -> torch.Tensor:
        """Normalised state (B, state_dim), followed by the tcp features (B, 9) when `tcp_features`
        is on -> Q_s (B, hidden)."""
        return self.state_encoder(state, embodiment_id)

    def aggregate_dynamics(self, static: torch.Tensor, wrist: torch.Tensor) -> torch.Tensor:
        """F_p of both views (B, T, C, H_p, W_p) -> Q_p (B, T*L, former_dim), eq. (4), on standardised features."""
        views = [standardize(f) for standardize, f in zip(self.dynamics_standardizers, (static, wrist))]
        return self.video_former(views)

    def conditions(
        self,
        q_s: torch.Tensor,
        q_vl: torch.Tensor | None,
        q_vl_mask: torch.Tensor | None,
        q_p: torch.Tensor | None,
        tcp: torch.Tensor | None = None,
        gripper: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """What the DiT reads: the state token Q_s (B, D) plus the instruction grounding's goal when
        configured (and, with `subgoal_offset`, the sub-goal seen from the tcp position); the
        cross-attention tokens [Q_vl; Q_p] at DiT width (B, M, D) and their mask (B, M); the grounding's
        predicted sub-goal (B, 3) in tcp feature units, or None without grounding. `tcp` (B, 9): the tool-centre
        point's features (panda_tcp), needed with `subgoal_offset`. `gripper` (B, 1): the gripper's closure
        (panda_gripper), needed with `grounding_reads_gripper`."""
        batch = q_s.shape[0]
        parts, masks = [], []
        subgoal = None
        if self.uses_vl:
            vl, vl_mask = self._vl_tokens(q_vl, q_vl_mask)
            if self.grounding is not None:
                if self.reads_tcp and (tcp is None or tuple(tcp.shape) != (batch, TCP_FEATURE_DIM)):
                    got = None if tcp is None else tuple(tcp.shape)
                    raise ValueError(f"tcp must be ({batch}, {TCP_FEATURE_DIM}), the tool-centre point's features "
                                     f"(policy.subgoal_offset); got {got}")
                goal, subgoal = self._ground(vl, vl_mask, gripper)
                q_s = q_s + goal.to(q_s.dtype)
                if self.subgoal_offset is not None:
                    q_s = q_s + self.subgoal_offset(subgoal, tcp[:, :3]).to(q_s.dtype)
            parts.append(vl)
            masks.append(vl_mask)
        if self.uses_dynamics:
            if q_p is None:
                raise ValueError("dynamics features are required: System 3 is enabled in this model")
            parts.append(self.dynamics_proj(q_p) + self.source_embed[1])
            masks.append(torch.ones(q_p.shape[:2], dtype=torch.bool, device=q_p.device))
        if not parts:
            parts.append(self.null_memory.unsqueeze(0).expand(batch, -1, -1))
            masks.append(torch.ones(batch, 1, dtype=torch.bool, device=self.null_memory.device))
        return q_s, torch.cat(parts, dim=1), torch.cat(masks, dim=1), subgoal

    def _vl_tokens(self, q_vl: torch.Tensor | None, q_vl_mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Q_vl (B, S, D_llm) -> standardised tokens at DiT width with their positions (B, S, D), mask (B, S)."""
        if q_vl is None:
            raise ValueError("q_vl is required: System 2 is enabled in this model")
        vl = self.vl_proj(self.vl_norm(self.vl_standardizer(q_vl))) + self.source_embed[0]
        if self.vl_position is not None:
            fixed = self.vl_position.shape[0]
            vl = torch.cat([vl[:, :fixed] + self.vl_position.to(vl.dtype), vl[:, fixed:]], dim=1)
        mask = q_vl_mask if q_vl_mask is not None else torch.ones(q_vl.shape[:2], dtype=torch.bool, device=q_vl.device)
        return vl, mask

    @property
    def reads_tcp(self) -> bool:
        """Whether conditions() needs the tcp features (`subgoal_offset`)."""
        return self.subgoal_offset is not None

    def _new_grounding(self) -> InstructionGrounding:
        c = self.config
        return InstructionGrounding(c.hidden_size, c.num_heads, reads_gripper=c.grounding_reads_gripper)

    def _ground(self, vl: torch.Tensor, vl_mask: torch.Tensor,
                gripper: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        fixed = self.vl_fixed_positions
        return self.grounding(vl[:, fixed:], vl_mask[:, fixed:], vl[:, :fixed], gripper)

    def reset_grounding(self) -> None:
        """A fresh instruction grounding in place of this one (drawn from torch's global generator)."""
        if self.grounding is None:
            raise ValueError("this System 1 has no instruction grounding (policy.instruction_grounding is off)")
        old = next(self.grounding.parameters())
        self.grounding = self._new_grounding().to(old.device, old.dtype)

    def binding_parameters(self) -> dict[str, nn.Parameter]:
        """What binds the instruction's words to a place, by name: the instruction grounding but for its
        goal projection, and the Q_vl path it reads (vl_norm, vl_proj, vl_position). The `bind` phase of
        training trains exactly these; the `follow` phase keeps them (train/config.py, grounding_phase).
        The source embedding added to every Q_vl token is not among them: the DiT shares it, so follow
        still trains it, and the sub-goal can move a little (20/30 to 21/30 and 28/30 to 29/30 in the
        probe, research/instruction_grounding)."""
        if self.grounding is None:
            raise ValueError("this System 1 has no instruction grounding (policy.instruction_grounding is off)")
        return {name: p for name, p in self.named_parameters()
                if (name.startswith("grounding.") and not name.startswith("grounding.goal."))
                or name.split(".")[0] in ("vl_norm", "vl_proj", "vl_position")}

    def held_parameters(self) -> dict[str, nn.Parameter]:
        """The instruction grounding's held-block read-out by name (`grounding_reads_gripper`): what a bind
        run with `bind_held_only` trains, leaving the answers with no block held as they were."""
        if self.grounding is None:
            raise ValueError("this System 1 has no instruction grounding (policy.instruction_grounding is off)")
        return {f"grounding.{name}": p for name, p in self.grounding.held_parameters().items()}

    def predict_subgoal(
        self, q_vl: torch.Tensor, q_vl_mask: torch.Tensor | None = None, gripper: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The instruction grounding's sub-goal (B, 3) in tcp feature units, from Q_vl (and, with
        `grounding_reads_gripper`, the gripper's closure (B, 1))."""
        return self.ground(q_vl, q_vl_mask, gripper)[1]

    def ground(
        self, q_vl: torch.Tensor, q_vl_mask: torch.Tensor | None = None, gripper: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The instruction grounding's goal token (B, D), which the DiT reads, and its sub-goal (as
        `predict_subgoal`), from Q_vl and the same optional inputs."""
        if self.grounding is None:
            raise ValueError("this System 1 has no instruction grounding (policy.instruction_grounding is off)")
        return self._ground(*self._vl_tokens(q_vl, q_vl_mask), gripper)

    # ------------------------------------------------------------------ flow matching

    def velocity(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        q_s: torch.Tensor,
        memory: torch.Tensor,
        memory_mask: torch.Tensor,
        embodiment_id: torch.Tensor,
    ) -> torch.Tensor:
        """Predicted velocity (B, H, A) of noisy normalised action chunks x (B, H, A) at flow times t (B,)."""
        actions = self.action_encoder(x, t, embodiment_id) + self.action_pos
        tokens = torch.cat([q_s.unsqueeze(1), actions], dim=1)
        out = self.dit(tokens, self.time_embed(t), memory, memory_mask)
        return self.action_decoder(out[:, 1:], embodiment_id)

    def loss(
        self,
        actions: torch.Tensor,
        q_s: torch.Tensor,
        memory: torch.Tensor,
        memory_mask: torch.Tensor,
        embodiment_id: torch.Tensor,
        *,
        action_mask: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Flow-matching loss on normalised action chunks (B, H, A); `action_mask` (B, H) drops padded steps."""
        c = self.config
        mask = None if action_mask is None else action_mask.unsqueeze(-1)
        return flow_matching.flow_matching_loss(
            lambda x, t: self.velocity(x, t, q_s, memory, memory_mask, embodiment_id),
            actions,
            alpha=c.time_beta_alpha,
            beta=c.time_beta_beta,
            s=c.time_s,
            generator=generator,
            mask=mask,
        )

    def sample(
        self,
        q_s: torch.Tensor,
        memory: torch.Tensor,
        memory_mask: torch.Tensor,
        embodiment_id: torch.Tensor,
        *,
        generator: torch.Generator | None = None,
        num_steps: int | None = None,
    ) -> torch.Tensor:
        """Normalised action chunks (B, H, A) by Euler integration from Gaussian noise of standard
        deviation `initial_noise_scale`."""
        c = self.config
        shape = (q_s.shape[0], c.action_horizon, c.action_dim)
        noise = torch.randn(shape, generator=generator, dtype=torch.float32).to(q_s.device, q_s.dtype)
        noise = noise * self.initial_noise_scale
        return flow_matching.euler_sample(
            lambda x, t: self.velocity(x, t, q_s, memory, memory_mask, embodiment_id),
            noise,
            num_steps or c.num_inference_steps,
        )
