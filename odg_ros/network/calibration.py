"""What the grid's numbers mean as probabilities, fitted on training worlds by ``odg export
--calibrate`` (train/calibrate.py) and applied inside the online step (static shapes, no
host read).

* **Voxel confidence**: the probability that the voxel's label is right. For an occupied
  voxel, that its class is right: per class, a logistic map of the logit of the voxel's mean
  top-class score (``sigmoid(scale_c * logit(score) + bias_c)``, a temperature and a shift
  per class). For a free voxel, that it is free: a logistic map of the log of its
  missed-occupancy hazard (below).
* **Missed-occupancy hazard**: how likely a ray through a voxel the grid calls free is stopped
  there by something the grid missed, per voxel length of the ray. It is read from what the
  grid holds in the voxel's column and in the 8 columns around it: per class present in the
  column, one rate for the free voxels between the column's lowest and highest occupied voxel
  and one for those above it, plus one rate per class present next to it (the free class's
  rates are the baseline of every column); 0 under the column's lowest occupied voxel (under
  the surface; the depth test handles it). The visibility (online/visibility.py) sums it along
  each camera ray: the ray is clear up to a voxel with probability exp(-sum).
* **Box score**: the probability that a published box is right (its class, centre within
  2 m): one logistic map of its score's logit, monotone, so the ranking and the boxes that
  pass ``box_score_threshold`` stay the same.

The grid's labels never change: the calibration reads them and the raw scores only.
A checkpoint without a calibration (``ModelConfig.calibration`` None) publishes the raw
scores (score x 255, 0 for free) and has no hazard.
"""
from __future__ import annotations

import math

import torch
from torch import nn

# the hazard's floor inside the free voxels' logistic map: log(0) would be -inf
HAZARD_FLOOR = 1e-4
# the raw score's range inside its logit: a score byte of 0 or 255 stays finite
SCORE_FLOOR = 0.5 / 255.0
# zone of a voxel in its column: 0 under the lowest occupied voxel, 1 between the lowest and
# highest, 2 above the highest (or in a column with nothing occupied); +4: occupied
UNDER, INSIDE, ABOVE, OCCUPIED = 0, 1, 2, 4
ZONES = 8


def logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(SCORE_FLOOR, 1.0 - SCORE_FLOOR)
    return torch.log(p) - torch.log1p(-p)


def check_calibration(values: dict, num_classes: int) -> None:
    """A clear error for a calibration dict that does not fit a model of ``num_classes``."""
    lengths = {"label_scale": num_classes, "label_bias": num_classes,
               "hazard_inside": num_classes + 1, "hazard_above": num_classes + 1,
               "hazard_near": num_classes}
    for key, length in lengths.items():
        if len(values.get(key, ())) != length:
            raise ValueError(f"calibration {key}: expected {length} values, got "
                             f"{len(values.get(key, ()))}")
    for key in ("free_scale", "free_bias"):
        if not isinstance(values.get(key), (int, float)):
            raise ValueError(f"calibration {key}: expected a number")
    box = values.get("box")
    if box is not None and (len(box) != 2 or box[0] <= 0):
        raise ValueError("calibration box: expected [scale > 0, bias] or null")
    numbers = [v for key in lengths for v in values[key]] + \
        [values["free_scale"], values["free_bias"]] + list(box or ())
    if not all(math.isfinite(v) for v in numbers):
        raise ValueError("calibration: a value is not finite")
    if min(v for key in ("hazard_inside", "hazard_above", "hazard_near")
           for v in values[key]) < 0:
        raise ValueError("calibration: a hazard rate is negative")


class Calibration(nn.Module):
    """The calibration of one model (``cfg.calibration``) on ``device``; ``calibrated`` is
    False without one (the confidence stays the raw score, no hazard)."""

    def __init__(self, cfg, device="cpu"):
        super().__init__()
        self.grid_shape = tuple(cfg.grid_shape)
        self.num_classes = cfg.num_classes
        self.free_label = cfg.num_classes
        values = cfg.calibration
        self.calibrated = values is not None
        C = self.num_classes
        if not self.calibrated:
            return
        check_calibration(values, C)
        f32 = dict(dtype=torch.float32, device=device)
        # occupied voxels: confidence byte by (label, raw score byte); the free label's row
        # is 0 (its confidence comes from the hazard)
        raw = torch.arange(256, **f32) / 255.0
        scale = torch.tensor(values["label_scale"], **f32)[:, None]
        bias = torch.tensor(values["label_bias"], **f32)[:, None]
        table = torch.sigmoid(scale * logit(raw) + bias)
        table = torch.cat([table, torch.zeros(1, 256, **f32)])
        self.register_buffer("label_table", (table * 255).round().to(torch.uint8).view(-1),
                             persistent=False)
        self.register_buffer("rates", torch.tensor(
            [values["hazard_inside"], values["hazard_above"]], **f32), persistent=False)
        self.register_buffer("near_rates", torch.tensor(values["hazard_near"], **f32),
                             persistent=False)
        self.free_scale, self.free_bias = float(values["free_scale"]), \
            float(values["free_bias"])
        box = values.get("box")
        self.box = None if box is None else (float(box[0]), float(box[1]))

    # ------------------------------------------------------------------- per column
    def column_hazards(self, present, near) -> torch.Tensor:
        """[ZONES, X, Y]: the hazard of a free voxel by its zone (0 for the others)."""
        C1, X, Y = present.shape
        flat = present.view(C1, X * Y).float()
        by_zone = self.rates @ flat + (self.near_rates @ near.view(C1 - 1, X * Y).float())
        zero = torch.zeros_like(by_zone[0])
        return torch.stack([zero, by_zone[0], by_zone[1]] + [zero] * (ZONES - 3)).view(
            ZONES, X, Y)

    # ---------------------------------------------------------------------- outputs
    def forward(self, labels: torch.Tensor, confidence: torch.Tensor):
        """labels, confidence uint8 [X*Y*Z] (the raw score x 255) -> (the calibrated
        confidence uint8 [X*Y*Z], the hazard float [X*Y*Z] or None without a
        calibration)."""
        if not self.calibrated:
            return confidence, None
        X, Y, Z = self.grid_shape
        present, near, zone = column_features(labels, self.grid_shape, self.num_classes)
        hazards = self.column_hazards(present, near)                      # [ZONES, X, Y]
        # one look-up per voxel from its column's table of zones
        index = (torch.arange(X * Y, device=labels.device).view(X, Y, 1) * ZONES
                 + zone).view(-1)
        hazard = hazards.permute(1, 2, 0).reshape(-1).index_select(0, index)
        free = 1.0 - torch.sigmoid(self.free_scale * torch.log(hazards + HAZARD_FLOOR)
                                   + self.free_bias)
        free_bytes = torch.where(torch.arange(ZONES, device=labels.device)[:, None, None]
                                 < OCCUPIED, (free * 255).round(), torch.zeros_like(free))
        free_bytes = free_bytes.to(torch.uint8).permute(1, 2, 0).reshape(-1)
        occupied = self.label_table.index_select(
            0, (labels.int() * 256 + confidence.int()).view(-1))
        return free_bytes.index_select(0, index) + occupied, hazard

    def box_score(self, score: torch.Tensor) -> torch.Tensor:
        """Box scores [..] -> the probability that each box is right (as is without a box
        calibration)."""
        if not self.calibrated or self.box is None:
            return score
        return torch.sigmoid(self.box[0] * logit(score) + self.box[1])


def column_features(labels: torch.Tensor, grid_shape, num_classes: int):
    """labels uint8 [X*Y*Z] -> (which classes each column holds: uint8 [C + 1, X, Y], the
    free class last; which of the classes 0..C-1 the 3 x 3 columns around it hold: uint8
    [C, X, Y]; the zone of every voxel in its column: uint8 [X, Y, Z], UNDER, INSIDE or ABOVE,
    + OCCUPIED where occupied)."""
    X, Y, Z = grid_shape
    C = num_classes
    grid = labels.view(X * Y, Z)
    present = torch.zeros((C + 1, X * Y), dtype=torch.uint8, device=labels.device)
    present.scatter_(0, grid.transpose(0, 1).long(), 1)
    present = present.view(C + 1, X, Y)
    near = _max3x3(present[:C])
    occupied = grid != C                                                    # [X*Y, Z]
    layers = torch.arange(Z, device=labels.device)
    # the lowest and highest occupied layer of each column (-1: none)
    top = (occupied * (layers + 1)).amax(-1, keepdim=True) - 1
    bottom = torch.where(occupied.any(-1, keepdim=True),
                         Z - (occupied * (Z - layers)).amax(-1, keepdim=True),
                         torch.full_like(top, -1))
    zone = (layers > bottom).to(torch.uint8) + (layers > top).to(torch.uint8) \
        + occupied.to(torch.uint8) * OCCUPIED
    return present, near, zone.view(X, Y, Z)


def _max3x3(grid: torch.Tensor) -> torch.Tensor:
    """The 3 x 3 maximum of [C, X, Y] over its last two dimensions (the grid's edge as its
    own neighbour): two 3-wide passes."""
    for dim in (1, 2):
        n = grid.shape[dim]
        before = torch.cat([grid.narrow(dim, 0, 1), grid.narrow(dim, 0, n - 1)], dim)
        after = torch.cat([grid.narrow(dim, 1, n - 1), grid.narrow(dim, n - 1, 1)], dim)
        grid = torch.maximum(torch.maximum(grid, before), after)
    return grid
