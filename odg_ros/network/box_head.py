"""Box head on the dynamic queries (paper Eq. 13): a 10-d box code and 10 box class logits
per dynamic query and layer. Every layer refines all ten entries residually: the new code is
the previous layer's (detached) code plus a predicted residual, from a zero-initialised last
layer, so a new layer starts as the identity. SparseBEV refines only the centre this way and
predicts size, yaw and velocity anew in every layer; a residual velocity here means the
velocity that warps layer l + 1's sampling is layer l's estimate refined, never a fresh guess.

Box code: (cx, cy, cz [m, current ego], log w, log l, log h, sin yaw, cos yaw, vx, vy [m/s]).
"""
from __future__ import annotations

import torch
from torch import nn

from .gaussian_heads import class_branch, regression_branch
from .grid_range import GridRange

BOX_CODE_SIZE = 10


class BoxHead(nn.Module):
    def __init__(self, embed_dims: int, num_box_classes: int):
        super().__init__()
        self.cls = class_branch(embed_dims, num_box_classes)
        self.reg = regression_branch(embed_dims, BOX_CODE_SIZE)
        nn.init.zeros_(self.reg[-1].weight)
        nn.init.zeros_(self.reg[-1].bias)

    def forward(self, query: torch.Tensor, prev_boxes: torch.Tensor):
        """query [B, D, E], prev_boxes [B, D, 10] -> boxes [B, D, 10], logits [B, D, classes]."""
        return prev_boxes + self.reg(query), self.cls(query)


class BoxEncoder(nn.Module):
    """Embeds a dynamic query's box attributes for its position encoding (Eq. 13: the layer
    input for dynamic queries is means (+) box)."""

    def __init__(self, embed_dims: int, pc_range):
        super().__init__()
        self.grid = GridRange(pc_range)
        self.mlp = nn.Sequential(nn.Linear(BOX_CODE_SIZE, embed_dims), nn.LayerNorm(embed_dims),
                                 nn.ReLU(), nn.Linear(embed_dims, embed_dims))

    def forward(self, boxes: torch.Tensor) -> torch.Tensor:
        centre = self.grid.normalise(boxes[..., :3])
        return self.mlp(torch.cat([centre, boxes[..., 3:]], dim=-1))
