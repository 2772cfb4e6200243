"""OPUS's test-time padding of the predicted occupancy grid, applied after ``occupancy_grid``.

OPUS (``OPUSHead.get_occ`` with ``test_cfg.padding``, on in every OPUS config) fills small holes
between predicted voxels: per class, the grid of voxel scores is closed morphologically (a 3x3x3
max filter, then a 3x3x3 min filter, the grid border ignored). Voxels whose own score passed the
score threshold keep their label; every other voxel becomes the class with the largest closed
score if that score passes the threshold, else free.

``occupancy_grid`` hands on each voxel's label and its mean top-class score (quantised to
1/255), not the other classes' scores, so the per-class grids here hold the top class's score
and 0 for the other classes. Where OPUS would fill a voxel through a class that was nowhere the
top one, this does not.
"""
from __future__ import annotations

import torch


def _box_filter(grid: torch.Tensor, op) -> torch.Tensor:
    """3x3x3 max (op = torch.maximum) or min filter of [N, X, Y, Z], voxels outside the grid
    ignored; done as three 3-voxel passes, one per axis (the cube filter is separable).
    Out of place with the edge voxel as its own missing neighbour (op(v, v) = v), so the
    online step traces it as one graph (no ``out=`` into strided views)."""
    for dim in (1, 2, 3):
        n = grid.shape[dim]
        if n > 1:
            before = torch.cat([grid.narrow(dim, 0, 1), grid.narrow(dim, 0, n - 1)], dim)
            after = torch.cat([grid.narrow(dim, 1, n - 1), grid.narrow(dim, n - 1, 1)], dim)
            grid = op(op(grid, before), after)
    return grid


@torch.no_grad()
def pad_occupancy(labels: torch.Tensor, confidence: torch.Tensor, num_classes: int,
                  score_threshold: float):
    """labels uint8 [B, X, Y, Z] (num_classes = free), confidence uint8 [B, X, Y, Z] (score x
    255) -> the padded (labels, confidence), same shapes and dtypes. The filters run on the
    uint8 scores: max and min commute with the monotone map to [0, 1]."""
    B, X, Y, Z = labels.shape
    occupied = labels != num_classes
    confidence = torch.where(occupied, confidence, torch.zeros_like(confidence))
    per_class = torch.zeros((B, num_classes, X, Y, Z), dtype=torch.uint8, device=labels.device)
    per_class.scatter_(1, labels.long().clamp(max=num_classes - 1).unsqueeze(1),
                       confidence.unsqueeze(1))
    per_class = per_class.view(B * num_classes, X, Y, Z)
    closed = _box_filter(_box_filter(per_class, torch.maximum), torch.minimum)
    top, label = closed.view(B, num_classes, X, Y, Z).max(dim=1)
    keep = occupied & (confidence.float() / 255.0 > score_threshold)
    filled = ~keep & (top.float() / 255.0 > score_threshold)
    free = torch.full_like(labels, num_classes)
    new_labels = torch.where(keep, labels, torch.where(filled, label.to(labels.dtype), free))
    new_confidence = torch.where(keep | filled, torch.where(keep, confidence, top),
                                 torch.zeros_like(confidence))
    return new_labels, new_confidence
