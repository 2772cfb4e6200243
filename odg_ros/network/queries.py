"""Dual Gaussian queries (paper Sec. 3.2, Eq. 2-3): S static + D dynamic queries.

Every query has a feature vector and learnable initial Gaussian means, initialised from
U[0, 1] of the grid range. Dynamic queries also carry box attributes (Eq. 3:
log w, log l, log h, sin, cos, vx, vy; the box centre is the centroid of its means): the
size and yaw terms learnable from U[0, 1] as the paper says, the velocity zero and detached
as SparseBEV's: layer 1's velocity warp starts from a still object instead of a random
0-1 m/s drift, and its residual velocity is the first estimate. (A checkpoint trained with
a learnable initial velocity keeps its stored values; they just no longer train.)
"""
from __future__ import annotations

import torch
from torch import nn

from .grid_range import GridRange


class DualGaussianQueries(nn.Module):
    def __init__(self, num_dynamic: int, num_static: int, embed_dims: int, pc_range):
        super().__init__()
        self.num_dynamic = num_dynamic
        self.num_static = num_static
        self.grid = GridRange(pc_range)
        num = num_dynamic + num_static
        self.features = nn.Parameter(torch.zeros(num, embed_dims))
        self.init_points = nn.Parameter(torch.rand(num, 1, 3))        # normalised, U[0, 1]
        self.init_box = nn.Parameter(torch.rand(num_dynamic, 7))      # U[0, 1], paper Sec. 3.2
        with torch.no_grad():
            self.init_box[:, 5:7] = 0.0                                # vx, vy: see above

    def forward(self, batch_size: int):
        """-> features [B, Q, E], means [B, Q, 1, 3] metres, boxes [B, D, 10] or None."""
        features = self.features.unsqueeze(0).expand(batch_size, -1, -1)
        means = self.grid.metres(self.init_points)
        means = means.unsqueeze(0).expand(batch_size, -1, -1, -1)
        boxes = None
        if self.num_dynamic:
            centre = means[:, :self.num_dynamic, 0]
            attrs = torch.cat([self.init_box[:, :5], self.init_box[:, 5:7].detach()], dim=-1)
            attrs = attrs.unsqueeze(0).expand(batch_size, -1, -1)
            boxes = torch.cat([centre, attrs], dim=-1)
        return features, means, boxes
