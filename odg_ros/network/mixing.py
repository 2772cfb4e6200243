"""Adaptive mixing (AdaMixer): per-query generated channel and point mixing of the sampled
features, then a projection back to the query dimension (residual)."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class AdaptiveMixing(nn.Module):
    def __init__(self, embed_dims: int, num_groups: int, in_points: int, out_points: int):
        super().__init__()
        self.G = num_groups
        self.c = embed_dims // num_groups
        self.in_points = in_points
        self.out_points = out_points
        self.channel_params = self.c * self.c
        self.point_params = in_points * out_points
        self.generator = nn.Linear(embed_dims,
                                   num_groups * (self.channel_params + self.point_params))
        self.out_proj = nn.Linear(num_groups * out_points * self.c, embed_dims)
        nn.init.zeros_(self.generator.weight)

    def forward(self, sampled: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
        """sampled [B, Q, G, P_in, c], query [B, Q, E] -> query [B, Q, E]."""
        B, Q = query.shape[:2]
        params = self.generator(query).view(B, Q, self.G, -1)
        M, S = params.split([self.channel_params, self.point_params], dim=-1)
        M = M.view(B, Q, self.G, self.c, self.c)
        S = S.view(B, Q, self.G, self.out_points, self.in_points)
        x = F.relu(F.layer_norm(sampled @ M, sampled.shape[-2:]))         # channel mixing
        x = S @ x                                                          # point mixing
        x = F.relu(F.layer_norm(x, x.shape[-2:]))
        return query + self.out_proj(x.reshape(B, Q, -1))
