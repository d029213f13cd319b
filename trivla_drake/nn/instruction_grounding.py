"""System 1's instruction grounding: which place in the images the instruction's words name.

System 1's action tokens cross-attend to Q_vl, but they are made from noise, the flow time and the
state: they do not know the instruction, so their first attention cannot look for "the red block".
Finding it takes two hops (read the colour word, then find that colour in the images), and the
flow-matching loss alone did not teach them (results/system2_positions). This module makes it one
hop: the instruction's tokens attend over the position-embedded image tokens.
The read-out predicts the next gripper event's tool-centre-point position (data/subgoals.py), a
dense auxiliary loss, and enters the DiT as a goal added to the state token Q_s.

Positions are in panda_tcp's feature units, (p - centre) / scale, the same as the state token's
tool-centre-point features, so the DiT can compare them. With `yaw_tokens`, it also predicts the
hand's yaw at that event modulo a quarter turn, as (cos 4 psi, sin 4 psi) (data/subgoals.py): which
way the block's faces turn: most of the shipped model's failed grasps came down 40-45 degrees off the
faces, its fingers on the block's top. (Read from the images, this yaw learnt a shortcut from the
demonstrations, in which the hand is always turned right near the block: results/grasp_yaw.)
With `reads_gripper`, a second read-out (its own queries, scores and sub-goal head) answers while a
block is held (nn/panda_gripper.py): "stack the red block on the blue one" names the red block before
the grasp and the blue one after it. Taught both with one read-out, a grounding put the sub-goal between
the two blocks before the grasp on unseen scenes (results/stack_carry, results/stack_phase).
With `anchor`, each read-out's chosen query also picks cells of the cameras' image tokens, and
the sub-goal is the places those cells look at (plus offsets) with the head's output added to it
(nn/token_anchor.py): the "where" from the camera's geometry, not regressed from one vector.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from trivla_drake.nn.attention import MultiHeadAttention
from trivla_drake.nn.panda_gripper import FEATURE_DIM as GRIPPER_FEATURE_DIM, holding_block
from trivla_drake.nn.panda_tcp import FEATURE_DIM as TCP_DIM, normalize_position
from trivla_drake.nn.token_anchor import TokenAnchor


YAW_TOKEN_FEATURES = 4  # features per image token in the yaw read-out


class InstructionGrounding(nn.Module):
    """Instruction tokens (B, S_t, D) + image tokens (B, S_i, D) -> goal (B, D), sub-goal (B, 3), or
    (B, 5) with `yaw_tokens`: the position, then (cos 4 psi, sin 4 psi) of the hand's yaw there.

    Every instruction token looks: its query attends over the image tokens ("red" finds the red
    block). A learned score per token then picks whose look counts (the colour word's, not "the").
    A mean of the instruction's tokens as one query would dilute the one word that names the object
    among the others (it did: its sub-goal hardly changed with the colour word)."""

    def __init__(self, dim: int, num_heads: int, tcp_dim: int = 0, yaw_tokens: int = 0,
                 reads_gripper: bool = False, anchor: TokenAnchor | None = None,
                 anchor_start: int = 0, anchor_wrist_start: int = 0) -> None:
        """`anchor`: the sub-goal's anchor on the image tokens (nn/token_anchor.py), reading the static view's
        from index `anchor_start` and, when it has wrist rays, the wrist view's from `anchor_wrist_start`
        (the tcp features are then required); None: the head's output is the sub-goal. `tcp_dim`: 0, or 9
        (nn/panda_tcp.py's features) for a head that reads them.

        The anchor's pick is added to the head's output. An anchor added to a trained grounding (a bind with
        --keep-grounding) so moves its sub-goal by the weighted places at first (tens of cm); the bind
        learns it back within its first few hundred steps (results/grounding_anchor: the binds' loss)."""
        if tcp_dim not in (0, TCP_DIM):
            raise ValueError(f"tcp_dim must be 0 or {TCP_DIM} (the tool-centre point's features); got {tcp_dim}")
        super().__init__()
        self.tcp_dim = tcp_dim
        # Words from tokens: System 2's tokenizer is byte-level, so "red" is three tokens; a convolution
        # over 5 neighbouring tokens (the longest colour word) composes them.
        self.compose = nn.Conv1d(dim, dim, kernel_size=5, padding=2)
        self.query = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim))
        self.score = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 1))
        self.attention = MultiHeadAttention(dim, num_heads)
        self.norm = nn.LayerNorm(dim)
        # The head reads the chosen query too: the sub-goal is where the named object is, shifted by
        # what the task does with it (a push ends beside the block, a lift above it).
        self.subgoal_head = nn.Sequential(nn.Linear(2 * dim + tcp_dim, dim), nn.SiLU(), nn.Linear(dim, 3))
        # `reads_gripper`: the read-out used while a block is held (panda_gripper.holding_block), the same
        # three parts again. The words and the image tokens' attention are shared; what differs is whose
        # look counts and where the sub-goal goes. `start_held_from_open` copies the other read-out into it.
        self.held = nn.ModuleDict({
            "query": nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim)),
            "score": nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 1)),
            "subgoal_head": nn.Sequential(nn.Linear(2 * dim + tcp_dim, dim), nn.SiLU(), nn.Linear(dim, 3)),
        }) if reads_gripper else None
        # With the tool-centre point's features (`tcp_dim` > 0, PolicyConfig.grounding_reads_tcp) the
        # head can place the sub-goal from the wrist view, relative to the gripper: a block seen in the
        # wrist view is an offset from the tcp, which a linear path adds (starting at zero).
        self.tcp_skip = nn.Linear(tcp_dim, 3) if tcp_dim else None
        if self.tcp_skip is not None:
            nn.init.zeros_(self.tcp_skip.weight)
            nn.init.zeros_(self.tcp_skip.bias)
        # The yaw (`yaw_tokens` > 0, the number of image tokens) is a linear read-out of every image token
        # in its place: a few features per token, flattened, then one linear map. An MLP on the attention's
        # read learnt the training scenes' yaws (2.9 degrees) and guessed on unseen ones (23, chance); a
        # ridge regression over the tokens in place found them on unseen scenes (results/grasp_yaw).
        self.yaw_tokens = yaw_tokens
        self.yaw_project = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, YAW_TOKEN_FEATURES)) if yaw_tokens else None
        self.yaw_head = nn.Linear(yaw_tokens * YAW_TOKEN_FEATURES, 2) if yaw_tokens else None
        self.anchor = anchor
        self.anchor_start = anchor_start
        self.anchor_wrist_start = anchor_wrist_start
        # The tcp features are read by the sub-goal head (tcp_dim > 0) and/or by the wrist view's anchor.
        self.reads_tcp = tcp_dim > 0 or (anchor is not None and anchor.wrist_cells > 0)
        self.goal = nn.Sequential(nn.Linear(dim + 3, dim), nn.SiLU(), nn.Linear(dim, dim))
        # The goal starts at zero, so a System 1 given this module starts as the one without it.
        nn.init.zeros_(self.goal[2].weight)
        nn.init.zeros_(self.goal[2].bias)

    def forward(
        self,
        instruction: torch.Tensor,
        instruction_mask: torch.Tensor,
        image_tokens: torch.Tensor,
        tcp: torch.Tensor | None = None,
        gripper: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each instruction token's query attends over the image tokens; their read-outs and queries
        are averaged with softmax weights of the tokens' scores (masked tokens get none). `tcp`
        (B, 9): the tool-centre point's features, required when built with tcp_dim > 0 or a wrist
        anchor and refused otherwise; `gripper` (B, 1): the gripper's closure (panda_gripper), likewise with
        `reads_gripper`. Returns the goal (B, D) for the DiT and the predicted sub-goal (B, 3) in
        feature units, followed with `yaw_tokens` by its (cos 4 psi, sin 4 psi) (B, 5 in all)."""
        batch = instruction.shape[0]
        if not self.reads_tcp and tcp is not None:
            raise ValueError("tcp was given to an instruction grounding built without tcp_dim or a wrist anchor")
        if self.reads_tcp and (tcp is None or tuple(tcp.shape) != (batch, TCP_DIM)):
            got = None if tcp is None else tuple(tcp.shape)
            raise ValueError(f"tcp must be ({batch}, {TCP_DIM}), the tool-centre point's features "
                             f"(policy.grounding_reads_tcp / grounding_anchor_wrist_camera); got {got}")
        if self.held is None and gripper is not None:
            raise ValueError("gripper was given to an instruction grounding built without reads_gripper")
        if self.held is not None and (gripper is None or tuple(gripper.shape) != (batch, GRIPPER_FEATURE_DIM)):
            got = None if gripper is None else tuple(gripper.shape)
            raise ValueError(f"gripper must be ({batch}, {GRIPPER_FEATURE_DIM}), the gripper's closure "
                             f"(policy.grounding_reads_gripper); got {got}")
        kept = instruction * instruction_mask.unsqueeze(-1).to(instruction.dtype)
        instruction = instruction + self.compose(kept.transpose(1, 2)).transpose(1, 2)
        if tcp is not None:
            tcp = tcp.to(instruction.dtype)
        cells = None
        if self.anchor is not None:
            static = image_tokens[:, self.anchor_start:self.anchor_start + self.anchor.places.shape[0]]
            wrist = (image_tokens[:, self.anchor_wrist_start:self.anchor_wrist_start + self.anchor.wrist_cells]
                     if self.anchor.wrist_cells else None)
            cells = self.anchor.cells(static, wrist, tcp if self.anchor.wrist_cells else None)
        read, subgoal = self._read(instruction, instruction_mask, image_tokens, tcp, cells,
                                   self.query, self.score, self.subgoal_head)
        if self.held is not None:
            # Both read-outs run on every row (a batch may mix phases, and every weight stays in the graph).
            held_read, held_subgoal = self._read(instruction, instruction_mask, image_tokens, tcp, cells,
                                                 self.held["query"], self.held["score"], self.held["subgoal_head"])
            held = holding_block(gripper).unsqueeze(-1)
            read, subgoal = torch.where(held, held_read, read), torch.where(held, held_subgoal, subgoal)
        if self.tcp_skip is not None:
            subgoal = subgoal + self.tcp_skip(tcp)
        goal = self.goal(torch.cat([read, subgoal], dim=-1))
        if self.yaw_head is not None:
            if image_tokens.shape[1] != self.yaw_tokens:
                raise ValueError(f"image_tokens must be (B, {self.yaw_tokens}, D) for the yaw read-out; "
                                 f"got {tuple(image_tokens.shape)}")
            # Detached: the yaw's loss leaves the tokens (and so the position's binding) as they are.
            yaw = self.yaw_head(self.yaw_project(image_tokens.detach()).flatten(1))
            subgoal = torch.cat([subgoal, yaw], dim=-1)
        return goal, subgoal

    def _read(self, instruction, instruction_mask, image_tokens, tcp, anchor_cells, query, score, subgoal_head):
        """One read-out: each token's query attends over the image tokens; their reads and queries are
        averaged with softmax weights of the tokens' scores -> the read (B, D) and the sub-goal (B, 3)
        (with an anchor, plus its pick of `anchor_cells`, TokenAnchor.cells())."""
        queries = query(instruction)
        reads = self.attention(queries, image_tokens)
        scores = score(instruction).squeeze(-1).masked_fill(~instruction_mask, float("-inf"))
        weights = torch.softmax(scores, dim=-1).nan_to_num(0.0).unsqueeze(-1)  # an all-masked row: zeros
        read = self.norm((weights * reads).sum(1))
        chosen = (weights * queries).sum(1)
        head_input = [read, chosen] + ([tcp] if self.tcp_skip is not None else [])
        subgoal = subgoal_head(torch.cat(head_input, dim=-1))
        if anchor_cells is not None:
            subgoal = subgoal + self.anchor.pick(chosen, anchor_cells)[0]
        return read, subgoal

    def start_held_from_open(self) -> None:
        """The held-block read-out set to a copy of the other one (a bind run that adds it starts here:
        the same answers in both phases, then only the carrying frames move it)."""
        if self.held is None:
            raise ValueError("this instruction grounding has no held-block read-out (built without reads_gripper)")
        for name in ("query", "score", "subgoal_head"):
            self.held[name].load_state_dict(getattr(self, name).state_dict())

    def held_parameters(self) -> dict[str, nn.Parameter]:
        """The held-block read-out's parameters by name (relative to this module)."""
        if self.held is None:
            raise ValueError("this instruction grounding has no held-block read-out (built without reads_gripper)")
        return {f"held.{name}": p for name, p in self.held.named_parameters()}


def grounding_loss(
    predicted: torch.Tensor, subgoal_position: torch.Tensor, counts: torch.Tensor | None = None,
    subgoal_yaw: torch.Tensor | None = None,
) -> torch.Tensor:
    """Smooth-L1 loss of predicted sub-goals (B, 3) in feature units against positions (B, 3) [m],
    averaged over the rows where `counts` (B,) bool is True (all rows when None; 0 when none counts,
    still connected to the graph). Sub-goals with a yaw (B, 5) also need `subgoal_yaw` (B, 2), the
    labels' (cos 4 psi, sin 4 psi), whose smooth-L1 loss is added (its read-out has weights of its own)."""
    target = normalize_position(subgoal_position).to(predicted.dtype)
    per_row = F.smooth_l1_loss(predicted[:, :3], target, beta=0.05, reduction="none").mean(-1)
    if predicted.shape[-1] == 5:
        if subgoal_yaw is None:
            raise ValueError("subgoal_yaw is required: this grounding also predicts the yaw (policy.subgoal_yaw)")
        yaw = F.smooth_l1_loss(predicted[:, 3:], subgoal_yaw.to(predicted.dtype), beta=0.05, reduction="none")
        per_row = per_row + yaw.mean(-1)
    if counts is None:
        return per_row.mean()
    weights = counts.to(per_row.dtype)
    return (per_row * weights).sum() / weights.sum().clamp(min=1.0)
