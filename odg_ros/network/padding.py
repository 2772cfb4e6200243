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

How it runs (a small share of the online step: static shapes, no host read, only
vectorised operations): the per-class grids are uint8 (max and min commute with the monotone
map to [0, 1]), each with a one-voxel border, in one flat buffer per chunk of classes (on the
CPU one class, whose grid and scratch stay in cache through all the passes; on a GPU all of
them). A 3-voxel pass of the separable filters along an axis is then two operations on the
whole buffer shifted by that axis's stride (1, a row, a plane), in place through one scratch
buffer: contiguous, no per-axis copies. The borders hold the neutral value, 0 for the max
filter and 255 for the min filter: "outside ignored" without edge cases. An interior voxel
only reads border voxels along the axis of its pass, which the passes before leave neutral;
the border is reset between the two filters. Each class's closed grid then updates the
running top score and its class. ``torch.where`` and comparisons with a number are avoided:
on the CPU both run element by element, ten to twenty times slower than the bit and clamp
operations of ``_select``, ``is_not`` and ``_passes``.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .uint8_compare import is_not


def passing_cutoff(score_threshold: float) -> int:
    """The smallest uint8 score s with ``s / 255 > score_threshold`` as the grid's float32
    arithmetic computes it (256: none passes), so the filters compare integers."""
    scores = np.arange(256, dtype=np.float32) / np.float32(255.0)
    passing = np.flatnonzero(scores > np.float32(score_threshold))
    return int(passing[0]) if len(passing) else 256


def _select(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``torch.where(mask, a, b)`` for uint8 ``a``, ``b`` as bit operations (mask uint8 0 or
    1)."""
    return b ^ ((a ^ b) & (mask * 255))                     # 255: all of a's bits


def _three_voxel_passes(flat: torch.Tensor, scratch: torch.Tensor, strides,
                        dilate: bool) -> None:
    """In place, each stride k in turn: flat[i] = max (dilate) or min of flat[i - k],
    flat[i], flat[i + k] (the first and last k positions: unchanged). ``scratch``: a buffer
    of flat's size for the pairs."""
    op = torch.maximum if dilate else torch.minimum
    for k in strides:
        pair = op(flat[:-k], flat[k:], out=scratch[:-k])         # pair[i]: i and i + k
        op(pair[:-k], pair[k:], out=flat[k:-k])


class OccupancyPadding(nn.Module):
    """``pad_occupancy`` for one grid shape, class count and score threshold (what the online
    step holds: the threshold's integer cut-off and the border pattern made once)."""

    def __init__(self, grid_shape, num_classes: int, score_threshold: float, device="cpu"):
        super().__init__()
        X, Y, Z = (int(s) for s in grid_shape)
        self.grid_shape, self.num_classes = (X, Y, Z), int(num_classes)
        self.cutoff = passing_cutoff(score_threshold)
        border = torch.full((X + 2, Y + 2, Z + 2), 255, dtype=torch.uint8, device=device)
        border[1:-1, 1:-1, 1:-1] = 0
        self.register_buffer("border", border.view(-1), persistent=False)
        self.strides = (1, Z + 2, (Y + 2) * (Z + 2))        # innermost axis first
        # classes filtered together: on the CPU one at a time (its grid and scratch, 1.5 MB,
        # stay in cache through the twelve passes: a third faster than all at once); on a
        # GPU all at once (fewer launches)
        self.chunk = 1 if torch.device(device).type == "cpu" else self.num_classes

    def _passes(self, score: torch.Tensor) -> torch.Tensor:
        """uint8 scores -> uint8 1 where the score passes the threshold, else 0."""
        if self.cutoff > 255:
            return torch.zeros_like(score)
        if self.cutoff == 0:
            return torch.ones_like(score)
        # score >= cutoff without a comparison with a number (see is_not)
        return score.clamp(min=self.cutoff - 1).sub_(self.cutoff - 1).clamp_(max=1)

    @torch.no_grad()
    def forward(self, labels: torch.Tensor, confidence: torch.Tensor):
        """labels uint8 [B, X, Y, Z] (num_classes = free), confidence uint8 [B, X, Y, Z]
        (score x 255) -> the padded (labels, confidence), same shapes and dtypes."""
        B = labels.shape[0]
        C, (X, Y, Z) = self.num_classes, self.grid_shape
        occupied = is_not(labels, C)
        confidence = confidence * occupied
        # in the bordered layout: each voxel's class (a free voxel's does not matter: its
        # score is 0) and score, the border free
        padding = (1, 1, 1, 1, 1, 1)
        classes = nn.functional.pad(labels.clamp(max=C - 1), padding, value=C).view(B, -1)
        scores = nn.functional.pad(confidence, padding).view(B, -1)
        top = label = None
        for first in range(0, C, self.chunk):
            chunk = range(first, min(first + self.chunk, C))
            grids = torch.empty((B, len(chunk), scores.shape[1]), dtype=torch.uint8,
                                device=labels.device)
            for i, c in enumerate(chunk):           # the class's scores, 0 elsewhere
                torch.bitwise_and(scores, is_not(classes, c).sub_(1), out=grids[:, i])
            flat, scratch = grids.view(-1), torch.empty_like(grids.view(-1))
            _three_voxel_passes(flat, scratch, self.strides, dilate=True)
            grids.view(-1, scores.shape[1]).bitwise_or_(self.border)  # the min filter's: 255
            _three_voxel_passes(flat, scratch, self.strides, dilate=False)
            for i, c in enumerate(chunk):
                closed = grids[:, i]
                if top is None:
                    top, label = closed.clone(), torch.zeros_like(closed)
                    continue
                # the largest closed score and the first class that has it (as max(dim)
                # picks): classes in order, a strictly larger score takes the voxel; the
                # labels so far are all below c, so a maximum sets c there
                torch.maximum(label, (closed > top).to(torch.uint8).mul_(c), out=label)
                torch.maximum(top, closed, out=top)
        top, label = (t.view(B, X + 2, Y + 2, Z + 2)[:, 1:-1, 1:-1, 1:-1] for t in (top, label))
        keep = occupied & self._passes(confidence)
        filled = (keep ^ 1) & self._passes(top)
        free = torch.full_like(labels, C)
        new_labels = _select(keep, labels, _select(filled, label, free))
        new_confidence = _select(keep, confidence, top * filled)
        return new_labels, new_confidence


@torch.no_grad()
def pad_occupancy(labels: torch.Tensor, confidence: torch.Tensor, num_classes: int,
                  score_threshold: float):
    """labels uint8 [B, X, Y, Z] (num_classes = free), confidence uint8 [B, X, Y, Z] (score x
    255) -> the padded (labels, confidence), same shapes and dtypes."""
    padding = OccupancyPadding(labels.shape[1:], num_classes, score_threshold,
                               device=labels.device)
    return padding(labels, confidence)
