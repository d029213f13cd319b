"""A sub-goal anchored on the image cells a query picks: a spatial soft-argmax over a fixed camera's tokens.

The instruction grounding's sub-goal head regresses a position from one attention read: a vector that
must carry "where" through an MLP. Its sub-goals landed a median 2.6-3.5 cm from the named block, and a
grasp holds only about 1.5 cm off (results/missed_grasps). Here the "where" is geometry instead: each of
a fixed camera's image tokens looks at a known place on the table (nn/camera_cells.py), the query's
softmax over the tokens weighs those places, and each token adds an offset read from its own features
(System 2's dense loss taught a token where in its cell a block lies: results/subcell_dense). The
places are parameters, started at the camera's geometry, so training may move them.

Near a grasp the arm hides the block from the static camera, and the wrist camera shows it large. With
`wrist_rays`, the wrist view's tokens join the softmax: their places are where their cells' rays meet the
table, from the hand's pose (the tool-centre point's features, nn/panda_tcp.py) and the wrist camera's
fixed pose on the hand, computed on every call. A cell whose ray does not come down to the table gets no
weight.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from trivla_drake.nn.panda_tcp import denormalize_position, normalize_position


class TokenAnchor(nn.Module):
    """Query (B, D) + a fixed camera's image tokens (B, N, D) -> an anchor position (B, 3) in tcp feature
    units (nn/panda_tcp.normalize_position): sum_i softmax_i(q . k_i) (place_i + offset(token_i))."""

    # Positions: the optimizer does not decay them toward the origin (train/trainer.py).
    NO_WEIGHT_DECAY = ("places",)

    def __init__(self, dim: int, places: torch.Tensor, wrist_rays: torch.Tensor | None = None,
                 wrist_pose: tuple[torch.Tensor, torch.Tensor] | None = None, plane_height: float = 0.0) -> None:
        """`places` (N, 3) [m]: where each token's image cell looks on the table (nn/camera_cells.py).
        `wrist_rays` (M, 3): the wrist view's cell rays in its camera frame (nn/camera_cells.cell_rays),
        with `wrist_pose` (rotation (3, 3), position (3,) [m]), that camera in the tool-centre point's
        frame, and `plane_height` [m], the plane its places lie on."""
        super().__init__()
        if places.ndim != 2 or places.shape[1] != 3:
            raise ValueError(f"places must be (N, 3) positions [m]; got {tuple(places.shape)}")
        self.key = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim))
        self.query = nn.Linear(dim, dim)
        self.places = nn.Parameter(normalize_position(places.to(torch.float32)).clone())
        self.offset = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 3))
        nn.init.zeros_(self.offset[1].weight)  # starts at the places themselves
        nn.init.zeros_(self.offset[1].bias)
        self.scale = 1.0 / math.sqrt(dim)
        self.plane_height = plane_height
        self.wrist_cells = 0 if wrist_rays is None else wrist_rays.shape[0]
        if wrist_rays is not None:
            if wrist_pose is None or wrist_rays.ndim != 2 or wrist_rays.shape[1] != 3:
                raise ValueError("wrist_rays must be (M, 3) directions, given with wrist_pose")
            # The rays in the tcp frame and the camera's origin there: fixed geometry, saved with the weights.
            self.register_buffer("wrist_rays_in_tcp", (wrist_rays.float() @ wrist_pose[0].float().T).contiguous())
            self.register_buffer("wrist_origin_in_tcp", wrist_pose[1].float().clone())

    def forward(self, query: torch.Tensor, tokens: torch.Tensor, wrist_tokens: torch.Tensor | None = None,
                tcp: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (anchor (B, 3) in feature units, the softmax weights over the tokens (B, N [+ M])). With
        wrist rays, also the wrist view's tokens (B, M, D) and the tcp features (B, 9) (nn/panda_tcp.py)."""
        return self.pick(query, self.cells(tokens, wrist_tokens, tcp))

    def cells(self, tokens: torch.Tensor, wrist_tokens: torch.Tensor | None = None,
              tcp: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """What every query's pick reads, computed once per forward (a grounding's two read-outs share it):
        the cells' keys (B, N [+ M], D), their points (place + offset, B, N [+ M], 3, feature units) and,
        with wrist rays, which cells look at the table (B, N + M) bool (None without)."""
        if tokens.shape[1] != self.places.shape[0]:
            raise ValueError(f"tokens must be (B, {self.places.shape[0]}, D), one per anchored image cell; "
                             f"got {tuple(tokens.shape)}")
        batch = tokens.shape[0]
        places = self.places.to(tokens.dtype).expand(batch, -1, -1)
        valid = None
        if self.wrist_cells:
            if wrist_tokens is None or tuple(wrist_tokens.shape[:2]) != (batch, self.wrist_cells):
                got = None if wrist_tokens is None else tuple(wrist_tokens.shape)
                raise ValueError(f"wrist_tokens must be ({batch}, {self.wrist_cells}, D), the wrist view's; got {got}")
            if tcp is None or tuple(tcp.shape) != (batch, 9):
                got = None if tcp is None else tuple(tcp.shape)
                raise ValueError(f"tcp must be ({batch}, 9), the tool-centre point's features; got {got}")
            wrist_places, wrist_valid = self.wrist_places(tcp)
            tokens = torch.cat([tokens, wrist_tokens], dim=1)
            places = torch.cat([places, wrist_places.to(tokens.dtype)], dim=1)
            valid = torch.cat([torch.ones_like(wrist_valid[:, :1]).expand(-1, self.places.shape[0]), wrist_valid], 1)
        return self.key(tokens), places + self.offset(tokens), valid

    def pick(self, query: torch.Tensor, cells: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """One query (B, D) over `cells` (from cells()) -> (anchor (B, 3), softmax weights (B, N [+ M]))."""
        keys, points, valid = cells
        logits = torch.einsum("bd,bnd->bn", self.query(query), keys) * self.scale
        if valid is not None:
            logits = logits.masked_fill(~valid, float("-inf"))
        weights = torch.softmax(logits, dim=-1)
        return torch.einsum("bn,bnc->bc", weights, points.to(weights.dtype)), weights

    def wrist_places(self, tcp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Where the wrist view's cell rays meet the plane, in feature units (B, M, 3), and which do (B, M)
        bool, from the tcp features (B, 9): position in feature units, the rotation's first two columns.
        Computed in float32 whatever the caller's dtype or autocast (bfloat16 would cost millimetres)."""
        with torch.autocast(device_type=tcp.device.type, enabled=False):
            return self._wrist_places(tcp.float())

    def _wrist_places(self, tcp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        position = denormalize_position(tcp[:, :3])
        first, second = tcp[:, 3:6], tcp[:, 6:9]
        rotation = torch.stack([first, second, torch.linalg.cross(first, second)], dim=-1)  # columns
        origin = position + rotation @ self.wrist_origin_in_tcp.float()
        rays = self.wrist_rays_in_tcp.float() @ rotation.transpose(1, 2)  # (B, M, 3) in the world
        down = rays[..., 2]
        reach = (self.plane_height - origin[:, 2:3]) / down.clamp(max=-1e-6)
        valid = (down < -1e-3) & (reach > 0)
        points = origin[:, None, :] + reach.clamp(min=0.0, max=5.0)[..., None] * rays
        return normalize_position(points), valid
