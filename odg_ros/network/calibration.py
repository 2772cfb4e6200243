"""What the grid's numbers mean as probabilities, fitted on training worlds by ``odg export
--calibrate`` (train/calibrate.py) and applied inside the online step (static shapes, no
host read).

* **Voxel confidence**: the probability that the voxel's label is right. For an occupied
  voxel, that its class is right: per class, a logistic map of the logit of the voxel's mean
  top-class score (``sigmoid(scale_c * logit(score) + bias_c)``, a temperature and a shift
  per class). For a free voxel, that it is free: a logistic map of the log of its
  missed-occupancy hazard (below).
* **Missed-occupancy hazard**: how likely a ray through a voxel the grid calls free is stopped
  there by something the grid missed, per voxel length of the ray. A sum of rates, each for
  one fact about the voxel and the classes the grid holds around it (``HAZARD_RATES``): per
  class in its own column, where the voxel lies in that column (between the lowest and
  highest occupied voxel, up to 1.6 m above the highest, higher); per class in the 8
  columns around it, or in the ring of 16 around those, and whether the voxel is at the
  height of a car's or a person's body (``BODY``, 0-2 m). The free class's rates are the
  baseline of every column. 0 under a column's lowest occupied voxel (under the surface:
  the depth test handles it). The visibility (network/visibility.py) sums it along each
  camera ray: the ray is clear up to a voxel with probability exp(-sum).
* **Box score**: the probability that a published box is right (its class, centre within
  2 m): one logistic map of its score's logit, monotone, so the ranking and the boxes that
  pass ``box_score_threshold`` stay the same.

The grid's labels never change: the calibration reads them and the raw scores only.
A checkpoint without a calibration (``ModelConfig.calibration`` None) publishes the raw
scores (score x 255, 0 for free) and has no hazard.
"""
from __future__ import annotations

import torch
from torch import nn

from ..model_config import HAZARD_RATES, check_calibration, rate_lengths  # noqa: F401

# the hazard's floor inside the free voxels' logistic map: log(0) would be -inf
HAZARD_FLOOR = 1e-4
# the raw score's range inside its logit: a score byte of 0 or 255 stays finite
SCORE_FLOOR = 0.5 / 255.0
# where a free voxel lies in its column: under the lowest occupied voxel, between the lowest
# and the highest, up to ABOVE_LOW layers above the highest (or anywhere in a column with
# nothing occupied), higher; OCCUPIED: not free
UNDER, INSIDE, ABOVE_LOW, ABOVE_HIGH, OCCUPIED = 0, 1, 2, 3, 8
ABOVE_LOW_LAYERS = 4
# heights of a car's or a person's body (m, grid frame: the ground at 0)
BODY = (0.0, 2.0)
def logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(SCORE_FLOOR, 1.0 - SCORE_FLOOR)
    return torch.log(p) - torch.log1p(-p)


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
        # the rates as [which, class]: own column (inside, above low, above high) over C + 1
        # classes; around (near body, near other, ring body) over C
        self.register_buffer("own_rates", torch.tensor(
            [values[k] for k in ("hazard_inside", "hazard_above_low", "hazard_above_high")],
            **f32), persistent=False)
        self.register_buffer("around_rates", torch.tensor(
            [values[k] for k in ("hazard_near_body", "hazard_near_other", "hazard_ring_body")],
            **f32), persistent=False)
        self.free_scale, self.free_bias = float(values["free_scale"]), \
            float(values["free_bias"])
        box = values.get("box")
        self.box = None if box is None else (float(box[0]), float(box[1]))
        self.register_buffer("body", body_layers(cfg).to(torch.uint8).to(device),
                             persistent=False)
        X, Y, _ = self.grid_shape
        self.register_buffer("column_starts", torch.arange(X * Y, dtype=torch.int32,
                                                           device=device).view(X, Y, 1) * 16,
                             persistent=False)

    def column_hazards(self, features) -> torch.Tensor:
        """[X, Y, 16]: the hazard of a free voxel by its code (``voxel_codes``) in each
        column; 0 for the occupied ones."""
        present, near, ring, _ = features
        C1, X, Y = present.shape
        own = self.own_rates @ present.view(C1, X * Y).float()                 # [3, X*Y]
        near = near.view(C1 - 1, X * Y).float()
        around = torch.stack([self.around_rates[0] @ near + self.around_rates[2]
                              @ ring.view(C1 - 1, X * Y).float(),
                              self.around_rates[1] @ near])                      # [2, X*Y]
        zero = torch.zeros_like(own[0])
        # code = zone + 4 body height; UNDER gets nothing from around either
        by_code = [zero, own[0] + around[1], own[1] + around[1], own[2] + around[1],
                   zero, own[0] + around[0], own[1] + around[0], own[2] + around[0]]
        return torch.stack(by_code + [zero] * 8, -1).view(X, Y, 16)

    # ---------------------------------------------------------------------- outputs
    def forward(self, labels: torch.Tensor, confidence: torch.Tensor, hazard: bool = True):
        """labels, confidence uint8 [X*Y*Z] (the raw score x 255) -> (the calibrated
        confidence uint8 [X*Y*Z], the hazard float [X*Y*Z] or None without a calibration or
        ``hazard`` False: a step without the visibility reads none)."""
        if not self.calibrated:
            return confidence, None
        X, Y, Z = self.grid_shape
        features = column_features(labels, self.grid_shape, self.num_classes)
        hazards = self.column_hazards(features)                               # [X, Y, 16]
        # one look-up per voxel from its column's table of codes
        # (int32 throughout: a uint8 + int64 sum converts every voxel on the way)
        index = (voxel_codes(features[3], self.body).int() + self.column_starts).view(-1)
        per_voxel = hazards.view(-1).index_select(0, index) if hazard else None
        free = 1.0 - torch.sigmoid(self.free_scale * torch.log(hazards[..., :OCCUPIED]
                                                               + HAZARD_FLOOR) + self.free_bias)
        free_bytes = torch.cat([(free * 255).round().to(torch.uint8), torch.zeros_like(
            hazards[..., OCCUPIED:], dtype=torch.uint8)], -1)
        occupied = self.label_table.index_select(
            0, (labels.int() * 256 + confidence.int()).view(-1))
        return free_bytes.view(-1).index_select(0, index) + occupied, per_voxel

    def box_score(self, score: torch.Tensor) -> torch.Tensor:
        """Box scores [..] -> the probability that each box is right (as is without a box
        calibration)."""
        if not self.calibrated or self.box is None:
            return score
        return torch.sigmoid(self.box[0] * logit(score) + self.box[1])


def body_layers(cfg) -> torch.Tensor:
    """float [Z]: 1 for the layers whose centre lies at body height (``BODY``), else 0."""
    Z = cfg.grid_shape[2]
    centre = (torch.arange(Z, dtype=torch.float32) + 0.5) * cfg.voxel_size + cfg.pc_range[2]
    return ((centre > BODY[0]) & (centre <= BODY[1])).float()


def column_features(labels: torch.Tensor, grid_shape, num_classes: int):
    """labels uint8 [X*Y*Z] -> (which classes each column holds: uint8 [C + 1, X, Y], the
    free class last; which of the classes 0..C-1 the 3 x 3 columns around it hold, and which
    only the ring of 16 around those: uint8 [C, X, Y] each; the zone of every voxel in its
    column: uint8 [X, Y, Z], UNDER ... ABOVE_HIGH, or OCCUPIED).

    Per column, the classes and the occupied layers are bits of an int32, or-ed / summed
    down the column (no int64 index of every voxel: this runs in every step)."""
    X, Y, Z = grid_shape
    C = num_classes
    if C + 1 > 31 or Z > 24:
        raise ValueError(f"{C} classes, {Z} layers: at most 30 and 24 are supported")
    device = labels.device
    powers = 2 ** torch.arange(max(C + 1, Z), dtype=torch.int32, device=device)
    bits = powers.index_select(0, labels.int()).view(X * Y, Z)
    while bits.shape[1] % 2 == 0:         # an or down the column, halving it: 16 -> 8 -> ...
        half = bits.shape[1] // 2
        bits = bits[:, :half] | bits[:, half:]
    classes = _or_columns(bits)
    present = ((classes[None] & powers[:C + 1, None]) != 0).to(torch.uint8).view(C + 1, X, Y)
    near = _max3x3(present[:C])
    ring = _max3x3(near) - near
    occupied = (labels != C).view(X * Y, Z)
    # the occupied layers as bits (disjoint: a sum is an or); layer + 1 of the lowest and the
    # highest (0: none), from the lowest bit (m & -m) and the highest (log2, exact in float)
    layers = (occupied.int() * powers[:Z]).sum(-1, dtype=torch.int32, keepdim=True)
    some = (layers > 0).to(torch.uint8)
    top = (torch.log2(layers.float().clamp(min=1)).floor().to(torch.uint8) + 1) * some
    bottom = (torch.log2((layers & -layers).float().clamp(min=1)).to(torch.uint8) + 1) * some
    above_ground = torch.arange(1, Z + 1, dtype=torch.uint8, device=device)
    zone = (above_ground > bottom).to(torch.uint8) + (above_ground > top).to(torch.uint8) \
        + (above_ground > top + ABOVE_LOW_LAYERS).to(torch.uint8)
    zone = torch.where(occupied, torch.full_like(zone, OCCUPIED), zone)
    return present, near, ring, zone.view(X, Y, Z)


def _or_columns(bits: torch.Tensor) -> torch.Tensor:
    """The bitwise or of each row of an int32 [n, k]."""
    out = bits[:, 0]
    for i in range(1, bits.shape[1]):
        out = out | bits[:, i]
    return out


def voxel_codes(zone: torch.Tensor, body: torch.Tensor) -> torch.Tensor:
    """uint8 [X, Y, Z] codes 0..15 of the column tables: zone + 4 at body height (OCCUPIED:
    8); ``body`` uint8 [Z], 1 at body height."""
    return torch.where(zone == OCCUPIED, zone, zone + body * 4)


def hazard_indicators(labels: torch.Tensor, cfg, names=None):
    """{rate name: float [k, X, Y, Z]} of 0/1: which voxels each rate of HAZARD_RATES (per
    class) applies to, for fitting them (train/calibrate.py); ``names``: only these."""
    C = cfg.num_classes
    present, near, ring, zone = column_features(labels, cfg.grid_shape, C)
    body = body_layers(cfg).to(labels.device).bool()
    free = (zone == INSIDE) | (zone == ABOVE_LOW) | (zone == ABOVE_HIGH)
    where = {"hazard_inside": (zone == INSIDE, present),
             "hazard_above_low": (zone == ABOVE_LOW, present),
             "hazard_above_high": (zone == ABOVE_HIGH, present),
             "hazard_near_body": (free & body, near),
             "hazard_near_other": (free & ~body, near),
             "hazard_ring_body": (free & body, ring)}
    return {name: (where[name][0][None] & where[name][1][..., None].bool()).float()
            for name in (names or HAZARD_RATES)}


def _max3x3(grid: torch.Tensor) -> torch.Tensor:
    """The 3 x 3 maximum of [C, X, Y] over its last two dimensions (the grid's edge as its
    own neighbour): two 3-wide passes."""
    for dim in (1, 2):
        n = grid.shape[dim]
        before = torch.cat([grid.narrow(dim, 0, 1), grid.narrow(dim, 0, n - 1)], dim)
        after = torch.cat([grid.narrow(dim, 1, n - 1), grid.narrow(dim, n - 1, 1)], dim)
        grid = torch.maximum(torch.maximum(grid, before), after)
    return grid
