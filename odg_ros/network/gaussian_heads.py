"""Per-layer coarse-to-fine point heads and the shared Gaussian attribute MLPs.

* ``PointHead`` (one per layer): K_l new means per query, as metric offsets from the
  centroid of the query's previous means (OPUS refinement), and K_l x C class logits.
* ``Phi_s``, ``Phi_r``, ``Phi_sigma`` (paper Eq. 4-6, shared by all layers and both query
  sets): scale, unit quaternion and opacity of every Gaussian from its mean and its query
  feature.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from ..rotation import normalise_quaternions
from .grid_range import GridRange

CLASS_PRIOR = 0.01  # initial sigmoid score, focal-loss convention
MIN_SCALE, MAX_SCALE = 0.05, 1.6  # metres: from a fraction of a voxel to a bus side


def class_branch(embed_dims: int, out_dims: int) -> nn.Sequential:
    layers = []
    for _ in range(2):
        layers += [nn.Linear(embed_dims, embed_dims), nn.LayerNorm(embed_dims), nn.ReLU()]
    last = nn.Linear(embed_dims, out_dims)
    nn.init.constant_(last.bias, -math.log((1 - CLASS_PRIOR) / CLASS_PRIOR))
    return nn.Sequential(*layers, last)


def regression_branch(embed_dims: int, out_dims: int) -> nn.Sequential:
    layers = []
    for _ in range(2):
        layers += [nn.Linear(embed_dims, embed_dims), nn.ReLU()]
    return nn.Sequential(*layers, nn.Linear(embed_dims, out_dims))


class PointHead(nn.Module):
    def __init__(self, embed_dims: int, num_points: int, num_classes: int):
        super().__init__()
        self.K = num_points
        self.num_classes = num_classes
        self.cls = class_branch(embed_dims, num_classes * num_points)
        self.reg = regression_branch(embed_dims, 3 * num_points)

    def forward(self, query: torch.Tensor, centroid: torch.Tensor):
        """query [B, Q, E], centroid [B, Q, 3] -> means [B, Q, K, 3], logits [B, Q, K, C]."""
        B, Q, _ = query.shape
        means = centroid.unsqueeze(2) + self.reg(query).view(B, Q, self.K, 3)
        logits = self.cls(query).view(B, Q, self.K, self.num_classes)
        return means, logits


class GaussianAttributeMLP(nn.Module):
    """Phi(means, query feature) -> one Gaussian attribute per mean."""

    def __init__(self, embed_dims: int, out_dims: int, pc_range, hidden: int = 64):
        super().__init__()
        self.grid = GridRange(pc_range)
        self.from_query = nn.Linear(embed_dims, hidden)
        self.from_mean = nn.Linear(3, hidden)
        self.mlp = nn.Sequential(nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, out_dims))

    def forward(self, means: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
        """means [B, Q, K, 3] metres, query [B, Q, E] -> [B, Q, K, out_dims]."""
        normalised = self.grid.normalise(means)
        hidden = self.from_query(query).unsqueeze(2) + self.from_mean(normalised)
        return self.mlp(hidden)


class GaussianAttributes(nn.Module):
    """Phi_s, Phi_r, Phi_sigma."""

    def __init__(self, embed_dims: int, pc_range):
        super().__init__()
        self.phi_scale = GaussianAttributeMLP(embed_dims, 3, pc_range)
        self.phi_rotation = GaussianAttributeMLP(embed_dims, 4, pc_range)
        self.phi_opacity = GaussianAttributeMLP(embed_dims, 1, pc_range)
        with torch.no_grad():  # start near identity rotations
            self.phi_rotation.mlp[-1].bias.copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]))

    def forward(self, means: torch.Tensor, query: torch.Tensor):
        scales = MIN_SCALE + (MAX_SCALE - MIN_SCALE) * torch.sigmoid(self.phi_scale(means, query))
        rotations = normalise_quaternions(self.phi_rotation(means, query))
        opacities = torch.sigmoid(self.phi_opacity(means, query)).squeeze(-1)
        return scales, rotations, opacities
