"""System 1's instruction grounding: which place in the images the instruction's words name.

System 1's action tokens cross-attend to Q_vl, but they are made from noise, the flow time and the
state: they do not know the instruction, so their first attention cannot look for "the red block".
Finding it takes two hops (read the colour word, then find that colour in the images), and the
flow-matching loss alone did not teach them (research/system2_positions). This module makes it one
hop: the instruction's tokens attend over the position-embedded image tokens.
The read-out predicts the next gripper event's tool-centre-point position (data/subgoals.py), a
dense auxiliary loss, and enters the DiT as a goal added to the state token Q_s.

Positions are in panda_tcp's feature units, (p - centre) / scale, the same as the state token's
tool-centre-point features, so the DiT can compare them.
With `reads_gripper`, a second read-out (its own queries, scores and sub-goal head) answers while a
block is held (nn/panda_gripper.py): "stack the red block on the blue one" names the red block before
the grasp and the blue one after it. Taught both with one read-out, a grounding put the sub-goal between
the two blocks before the grasp on unseen scenes (research/stack_carry, research/stack_phase).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from trivla_drake.nn.attention import MultiHeadAttention
from trivla_drake.nn.panda_gripper import FEATURE_DIM as GRIPPER_FEATURE_DIM, holding_block
from trivla_drake.nn.panda_tcp import normalize_position


class InstructionGrounding(nn.Module):
    """Instruction tokens (B, S_t, D) + image tokens (B, S_i, D) -> goal (B, D), sub-goal (B, 3).

    Every instruction token looks: its query attends over the image tokens ("red" finds the red
    block). A learned score per token then picks whose look counts (the colour word's, not "the").
    A mean of the instruction's tokens as one query would dilute the one word that names the object
    among the others (it did: its sub-goal hardly changed with the colour word)."""

    def __init__(self, dim: int, num_heads: int, reads_gripper: bool = False) -> None:
        super().__init__()
        # Words from tokens: System 2's tokenizer is byte-level, so "red" is three tokens; a convolution
        # over 5 neighbouring tokens (the longest colour word) composes them.
        self.compose = nn.Conv1d(dim, dim, kernel_size=5, padding=2)
        self.query = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim))
        self.score = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 1))
        self.attention = MultiHeadAttention(dim, num_heads)
        self.norm = nn.LayerNorm(dim)
        # The head reads the chosen query too: the sub-goal is where the named object is, shifted by
        # what the task does with it (a push ends beside the block, a lift above it).
        self.subgoal_head = nn.Sequential(nn.Linear(2 * dim, dim), nn.SiLU(), nn.Linear(dim, 3))
        # `reads_gripper`: the read-out used while a block is held (panda_gripper.holding_block), the same
        # three parts again. The words and the image tokens' attention are shared; what differs is whose
        # look counts and where the sub-goal goes. `start_held_from_open` copies the other read-out into it.
        self.held = nn.ModuleDict({
            "query": nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim)),
            "score": nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 1)),
            "subgoal_head": nn.Sequential(nn.Linear(2 * dim, dim), nn.SiLU(), nn.Linear(dim, 3)),
        }) if reads_gripper else None
        self.goal = nn.Sequential(nn.Linear(dim + 3, dim), nn.SiLU(), nn.Linear(dim, dim))
        # The goal starts at zero, so a System 1 given this module starts as the one without it.
        nn.init.zeros_(self.goal[2].weight)
        nn.init.zeros_(self.goal[2].bias)

    def forward(
        self,
        instruction: torch.Tensor,
        instruction_mask: torch.Tensor,
        image_tokens: torch.Tensor,
        gripper: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Each instruction token's query attends over the image tokens; their read-outs and queries
        are averaged with softmax weights of the tokens' scores (masked tokens get none). `gripper`
        (B, 1): the gripper's closure (panda_gripper), required with `reads_gripper` and refused otherwise.
        Returns the goal (B, D) for the DiT and the predicted sub-goal (B, 3) in feature units."""
        batch = instruction.shape[0]
        if self.held is None and gripper is not None:
            raise ValueError("gripper was given to an instruction grounding built without reads_gripper")
        if self.held is not None and (gripper is None or tuple(gripper.shape) != (batch, GRIPPER_FEATURE_DIM)):
            got = None if gripper is None else tuple(gripper.shape)
            raise ValueError(f"gripper must be ({batch}, {GRIPPER_FEATURE_DIM}), the gripper's closure "
                             f"(policy.grounding_reads_gripper); got {got}")
        kept = instruction * instruction_mask.unsqueeze(-1).to(instruction.dtype)
        instruction = instruction + self.compose(kept.transpose(1, 2)).transpose(1, 2)
        read, subgoal = self._read(instruction, instruction_mask, image_tokens, self.query, self.score,
                                   self.subgoal_head)
        if self.held is not None:
            # Both read-outs run on every row (a batch may mix phases, and every weight stays in the graph).
            held_read, held_subgoal = self._read(instruction, instruction_mask, image_tokens, self.held["query"],
                                                 self.held["score"], self.held["subgoal_head"])
            held = holding_block(gripper).unsqueeze(-1)
            read, subgoal = torch.where(held, held_read, read), torch.where(held, held_subgoal, subgoal)
        goal = self.goal(torch.cat([read, subgoal], dim=-1))
        return goal, subgoal

    def _read(self, instruction, instruction_mask, image_tokens, query, score, subgoal_head):
        """One read-out: each token's query attends over the image tokens; their reads and queries are
        averaged with softmax weights of the tokens' scores -> the read (B, D) and the sub-goal (B, 3)."""
        queries = query(instruction)
        reads = self.attention(queries, image_tokens)
        scores = score(instruction).squeeze(-1).masked_fill(~instruction_mask, float("-inf"))
        weights = torch.softmax(scores, dim=-1).nan_to_num(0.0).unsqueeze(-1)  # an all-masked row: zeros
        read = self.norm((weights * reads).sum(1))
        chosen = (weights * queries).sum(1)
        subgoal = subgoal_head(torch.cat([read, chosen], dim=-1))
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
) -> torch.Tensor:
    """Smooth-L1 loss of predicted sub-goals (B, 3) in feature units against positions (B, 3) [m],
    averaged over the rows where `counts` (B,) bool is True (all rows when None; 0 when none counts,
    still connected to the graph)."""
    target = normalize_position(subgoal_position).to(predicted.dtype)
    per_row = F.smooth_l1_loss(predicted, target, beta=0.05, reduction="none").mean(-1)
    if counts is None:
        return per_row.mean()
    weights = counts.to(per_row.dtype)
    return (per_row * weights).sum() / weights.sum().clamp(min=1.0)
