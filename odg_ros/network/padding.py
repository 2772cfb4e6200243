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
import torch.nn.functional as F


@torch.no_grad()
def pad_occupancy(labels: torch.Tensor, confidence: torch.Tensor, num_classes: int,
                  score_threshold: float):
    """labels uint8 [B, X, Y, Z] (num_classes = free), confidence uint8 [B, X, Y, Z] (score x
    255) -> the padded (labels, confidence), same shapes and dtypes."""
    occupied = labels != num_classes
    score = confidence.float() / 255.0 * occupied
    per_class = torch.zeros((labels.shape[0], num_classes, *labels.shape[1:]),
                            dtype=torch.float32, device=labels.device)
    per_class.scatter_(1, labels.long().clamp(max=num_classes - 1).unsqueeze(1),
                       score.unsqueeze(1))
    dilated = F.max_pool3d(per_class, 3, stride=1, padding=1)       # the border pads with -inf
    closed = -F.max_pool3d(-dilated, 3, stride=1, padding=1)
    top, label = closed.max(dim=1)
    keep = occupied & (score > score_threshold)
    filled = ~keep & (top > score_threshold)
    new_labels = torch.where(keep, labels, torch.where(filled, label.to(labels.dtype),
                                                       torch.full_like(labels, num_classes)))
    new_confidence = torch.where(
        keep, confidence,
        torch.where(filled, (top * 255).round().clamp(0, 255).to(confidence.dtype),
                    torch.zeros_like(confidence)))
    return new_labels, new_confidence
