"""Occupancy loss (paper Eq. 9): Chamfer distance of the Gaussian means to the occupied voxel
centres, plus a sigmoid focal loss on each mean's class scores, the label being that of its
nearest occupied voxel.

The paper leaves the details to OPUS (Wang et al. 2024); what we read in OPUS's head
(``OPUSHead._get_target_single`` / ``loss_single`` / ``get_sparse_voxels`` and the
opus-{t,s,m,l} configs) and follow here:

* GT points: the centres ``(i + 0.5) * voxel + min`` of *every* non-free voxel, whatever the
  camera mask says. The camera mask only changes weights (below).
* Pairing: nearest neighbour in both directions (OPUS: ``mmcv.ops.knn`` under no_grad). The
  loss is then computed on the gathered coordinates, so gradients reach the predicted means
  through both directions.
* Point loss: mmdet ``SmoothL1Loss(beta=0.2, loss_weight=0.5)`` applied *per coordinate* of the
  difference (not to the Euclidean distance) and summed over x, y, z:
    pred -> GT: sum_n sum_xyz sl1(p_n - g_nn(n)) / (number of predicted points)
    GT -> pred: sum_g w_g sum_xyz sl1(g - p_nn(g)) / (number of GT points)
  with the per-GT weight w_g (OPUS train_cfg defaults, active in every released config):
    w_g = 1; w_g = 5 if the voxel is camera-visible and its nearest prediction is farther than
    0.2 m ("empty" GT, not yet covered); w_g = max(w_g, 10) if camera-visible and its class is a
    rare one (0 others, 2 bicycle, 5 construction_vehicle, 8 traffic_cone).
  Chamfer = 0.5 * (pred->GT + GT->pred). The normalisers are the plain point counts summed over
  the batch (mmdet avg_factor), not the sums of weights.
* Classification: mmdet ``FocalLoss(gamma=2, alpha=0.25, loss_weight=2.0)``, one-hot target
  from the nearest voxel's label. OPUS's weight is per (point, class *channel*), not per target
  class: weight[n, c] = cls_weights[c] * (1 + |xy(g_nn(n)) - xy(centre)| / |xy scene size|),
  the second factor up-weighting far points by at most 1.5. Normaliser: number of points.
* The initial points (layer 0) get the point loss only (OPUS: ``init_loss_pts``).

Our choices where OPUS has nothing to say: a sample with no occupied voxel adds nothing to the
Chamfer terms (and is left out of their normalisers), its points get all-negative focal targets
(class weight only) and it is counted in ``OccupancyLossResult.num_samples_without_gt``.

Nearest neighbours never build a full predictions-by-GT distance matrix (76,800 x ~40,000
floats = 12 GB at paper scale): on the CPU a k-d tree (scipy, O(N log M), ~0.1 s per
direction), elsewhere exact coordinate differences in blocks of at most ``max_block`` distances,
each block's minimum taken on the device (no host sync).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from ..classes import FREE_LABEL, OCC_CLASS_WEIGHTS
from ..transfer import device_constant, upload
from .focal import FOCAL_ALPHA, FOCAL_GAMMA, one_hot_targets, sigmoid_focal_loss

CHAMFER_BETA = 0.2         # SmoothL1 beta (m)
CHAMFER_WEIGHT = 0.5
OCC_FOCAL_WEIGHT = 2.0
EMPTY_DIST_THR = 0.2       # m: a visible GT voxel farther than this from every prediction ...
EMPTY_WEIGHT = 5.0         # ... weighs this much in the GT -> pred term
RARE_CLASSES = (0, 2, 5, 8)
RARE_WEIGHT = 10.0
MAX_BLOCK = 1 << 25        # distances per device block (128 MiB of float32)


# ---------------------------------------------------------------------------------------------
# nearest neighbours
# ---------------------------------------------------------------------------------------------

def block_rows(n: int, m: int, max_block: int) -> int:
    """Query rows per block so that a block holds at most ``max_block`` distances (one row
    when a single row is already larger)."""
    return max(1, min(n, max_block // max(m, 1)))


def _blocked_nearest(query: torch.Tensor, ref: torch.Tensor, max_block: int):
    """Exact search in blocks of whole query rows against every reference point.

    Distances are norms of coordinate differences (``cdist``'s direct mode, one kernel that
    never materialises the [rows, M, 3] differences): its default |a|^2 + |b|^2 - 2ab form
    loses the last millimetres to cancellation at 40 m and picks a wrong neighbour now and
    then. Each block's minimum is taken on the device and the blocks are
    concatenated, so the search never waits for the device (no boolean-mask updates); the
    number of blocks is n m / max_block, fixed by the sizes alone. Non-finite points give
    non-finite distances, which reach the loss (no check here would be free of a host sync).
    """
    n, m = query.shape[0], ref.shape[0]
    rows = block_rows(n, m, max_block)
    distances, indices = [], []
    for r0 in range(0, n, rows):
        block = torch.cdist(query[None, r0:r0 + rows], ref[None],
                            compute_mode="donot_use_mm_for_euclid_dist")[0]
        distance, index = block.min(dim=1)
        distances.append(distance)
        indices.append(index)
    return torch.cat(indices), torch.cat(distances)


class NearestNeighbourIndex:
    """Exact 3-D nearest-neighbour lookup into a fixed reference set ``ref`` [M, 3] (M >= 1).

    ``method``: "kdtree" (scipy, CPU, float64), "cdist" (blocked exact differences on the
    tensors' device, no host sync) or "auto" = kdtree for CPU tensors, cdist otherwise.
    Queries run without gradient. The k-d tree rejects non-finite points with a ValueError;
    the device search lets them through as non-finite distances (see _blocked_nearest).
    """

    def __init__(self, ref: torch.Tensor, method: str = "auto", max_block: int = MAX_BLOCK):
        if ref.dim() != 2 or ref.shape[1] != 3:
            raise ValueError(f"reference points must be [M, 3], got {tuple(ref.shape)}")
        if ref.shape[0] == 0:
            raise ValueError("nearest-neighbour search needs at least one reference point")
        if method == "auto":
            method = "kdtree" if ref.device.type == "cpu" else "cdist"
        if method not in ("kdtree", "cdist"):
            raise ValueError(f"unknown nearest-neighbour method {method!r}")
        self.method, self.max_block = method, max_block
        self.ref = ref.detach()
        self._tree = None
        if method == "kdtree":
            if not torch.isfinite(ref).all():
                raise ValueError("non-finite reference point in nearest-neighbour search")
            self._tree = cKDTree(self.ref.double().cpu().numpy())

    @torch.no_grad()
    def query(self, points: torch.Tensor):
        """points [N, 3] -> (index [N] long into ref, distance [N] in the dtype of points)."""
        if points.dim() != 2 or points.shape[1] != 3:
            raise ValueError(f"query points must be [N, 3], got {tuple(points.shape)}")
        points = points.detach()
        if points.shape[0] == 0:
            return (torch.zeros(0, dtype=torch.long, device=points.device),
                    torch.zeros(0, dtype=points.dtype, device=points.device))
        if self.method == "kdtree":
            if not torch.isfinite(points).all():
                raise ValueError("non-finite query point in nearest-neighbour search")
            dist, index = self._tree.query(points.double().cpu().numpy(), k=1)
            return (torch.from_numpy(np.asarray(index, dtype=np.int64)).to(points.device),
                    torch.from_numpy(dist).to(points.device, points.dtype))
        return _blocked_nearest(points, self.ref.to(points.dtype), self.max_block)


def nearest_neighbours(query: torch.Tensor, ref: torch.Tensor, method: str = "auto",
                       max_block: int = MAX_BLOCK):
    """query [N, 3], ref [M, 3] -> (index [N], distance [N]) of each query's nearest ref point."""
    return NearestNeighbourIndex(ref, method, max_block).query(query)


# ---------------------------------------------------------------------------------------------
# targets
# ---------------------------------------------------------------------------------------------

@dataclass
class OccupancyTarget:
    """One sample's occupied voxels: centres [M, 3] (m), labels [M] long, visible [M] bool."""
    centres: torch.Tensor
    labels: torch.Tensor
    visible: torch.Tensor
    method: str = "auto"
    _index: NearestNeighbourIndex | None = field(default=None, repr=False)

    @property
    def num(self) -> int:
        return int(self.centres.shape[0])

    def to(self, device) -> "OccupancyTarget":
        """The same target with its tensors on ``device`` (its search structure not built)."""
        return OccupancyTarget(upload(self.centres, device), upload(self.labels, device),
                               upload(self.visible, device), self.method)

    def nearest(self, points: torch.Tensor):
        """points [N, 3] -> (index [N], distance [N]) of each point's nearest occupied voxel.
        The search structure is built once and reused by every layer."""
        if self._index is None:
            self._index = NearestNeighbourIndex(self.centres, self.method)
        return self._index.query(points)


def occupancy_target(semantics: torch.Tensor, mask_camera: torch.Tensor,
                     pc_range: Sequence[float], voxel_size: float,
                     free_label: int = FREE_LABEL, method: str = "auto") -> OccupancyTarget:
    """Occ3D grid -> occupied voxel centres.

    semantics [X, Y, Z] int (free_label = free), mask_camera [X, Y, Z] bool, indexed [x, y, z];
    centre of voxel i along an axis = (i + 0.5) * voxel_size + pc_range[axis].
    Computed where the grid is; on the host (as in training) nothing waits for a device.
    """
    if semantics.dim() != 3 or semantics.shape != mask_camera.shape:
        raise ValueError(f"semantics {tuple(semantics.shape)} and mask_camera "
                         f"{tuple(mask_camera.shape)} must be the same [X, Y, Z] grid")
    expected = tuple(int(round((pc_range[i + 3] - pc_range[i]) / voxel_size)) for i in range(3))
    if tuple(semantics.shape) != expected:
        raise ValueError(f"occupancy grid {tuple(semantics.shape)} does not match pc_range "
                         f"{tuple(pc_range)} / voxel {voxel_size} = {expected}")
    labels = semantics.long()
    # one host read for the check, one for the number of occupied voxels
    if labels.numel() and bool(((labels < 0) | (labels > free_label)).any()):
        raise ValueError(f"occupancy labels outside [0, {free_label}]: "
                         f"min {int(labels.min())}, max {int(labels.max())}")
    ijk = (labels != free_label).nonzero()                           # [M, 3]
    i, j, k = ijk.unbind(-1)
    origin = torch.tensor(pc_range[:3], dtype=torch.float32, device=semantics.device)
    centres = (ijk.float() + 0.5) * voxel_size + origin
    return OccupancyTarget(centres=centres, labels=labels[i, j, k],
                           visible=mask_camera.bool()[i, j, k], method=method)


def gt_point_weights(target: OccupancyTarget, dist_to_pred: torch.Tensor) -> torch.Tensor:
    """OPUS per-GT weights of the GT -> pred term (see module docstring). [M] float."""
    uncovered = (dist_to_pred > EMPTY_DIST_THR) & target.visible
    weights = torch.where(uncovered, EMPTY_WEIGHT, 1.0).to(dist_to_pred.dtype)
    rare_classes = device_constant(RARE_CLASSES, target.labels.device, target.labels.dtype)
    rare = (target.labels[:, None] == rare_classes).any(-1) & target.visible
    return torch.where(rare, weights.clamp(min=RARE_WEIGHT), weights)


def distance_weight(points: torch.Tensor, pc_range: Sequence[float]) -> torch.Tensor:
    """OPUS: 1 + horizontal distance from the grid centre / horizontal grid diagonal. [N]."""
    centre = device_constant([(pc_range[0] + pc_range[3]) / 2, (pc_range[1] + pc_range[4]) / 2],
                             points.device, points.dtype)
    diagonal = math.hypot(pc_range[3] - pc_range[0], pc_range[4] - pc_range[1])
    return 1 + (points[:, :2] - centre).norm(dim=-1) / diagonal


# ---------------------------------------------------------------------------------------------
# loss
# ---------------------------------------------------------------------------------------------

def _at_least_float32(x: torch.Tensor) -> torch.Tensor:
    return x if x.dtype == torch.float64 else x.float()


@dataclass
class OccupancyLossResult:
    chamfer: torch.Tensor                 # scalar, includes CHAMFER_WEIGHT
    focal: torch.Tensor | None            # scalar, includes OCC_FOCAL_WEIGHT; None without logits
    num_samples_without_gt: int


def occupancy_loss(points: torch.Tensor, logits: torch.Tensor | None,
                   targets: Sequence[OccupancyTarget], pc_range: Sequence[float],
                   class_weights: Sequence[float] = OCC_CLASS_WEIGHTS,
                   beta: float = CHAMFER_BETA, chamfer_weight: float = CHAMFER_WEIGHT,
                   focal_weight: float = OCC_FOCAL_WEIGHT,
                   alpha: float = FOCAL_ALPHA, gamma: float = FOCAL_GAMMA) -> OccupancyLossResult:
    """Chamfer (+ focal) loss of one layer.

    points [B, N, 3] predicted means (m, current ego frame); logits [B, N, C] or None (initial
    points); targets: B OccupancyTarget. Half precision is computed in float32, float64 stays.
    """
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be [B, N, 3], got {tuple(points.shape)}")
    if len(targets) != points.shape[0]:
        raise ValueError(f"{points.shape[0]} samples but {len(targets)} targets")
    if logits is not None and logits.shape[:2] != points.shape[:2]:
        raise ValueError(f"logits {tuple(logits.shape)} do not match points {tuple(points.shape)}")
    points = _at_least_float32(points)
    if logits is not None:
        logits = _at_least_float32(logits)
        if logits.shape[-1] != len(class_weights):
            raise ValueError(f"{logits.shape[-1]} class logits but {len(class_weights)} weights")
        cls_w = device_constant(class_weights, points.device, points.dtype)

    pred_sum = gt_sum = focal_sum = points.new_zeros(())
    num_pred = num_gt = num_focal = num_empty = 0
    for b, target in enumerate(targets):
        pts = points[b]
        if target.num == 0:
            num_empty += 1
            if logits is not None:
                fl = sigmoid_focal_loss(logits[b], torch.zeros_like(logits[b]), alpha, gamma)
                focal_sum = focal_sum + (fl * cls_w).sum()
                num_focal += pts.shape[0]
            continue
        if pts.shape[0] == 0:   # the GT -> pred term has no nearest prediction to pull
            raise ValueError(f"sample {b}: no predicted points to match its {target.num} "
                             "occupied voxels")
        centres = target.centres.to(pts.device, pts.dtype)
        pred_to_gt, _ = target.nearest(pts)
        gt_to_pred, _ = NearestNeighbourIndex(pts, target.method).query(centres)
        # pred -> GT: every predicted point is pulled to its nearest occupied voxel centre
        pred_sum = pred_sum + F.smooth_l1_loss(pts, centres[pred_to_gt], beta=beta,
                                               reduction="none").sum()
        # GT -> pred: every occupied voxel pulls its nearest prediction, weighted (OPUS)
        paired = pts[gt_to_pred]
        with torch.no_grad():
            weights = gt_point_weights(target, (centres - paired).norm(dim=-1))
        gt_sum = gt_sum + (weights[:, None] * F.smooth_l1_loss(
            paired, centres, beta=beta, reduction="none")).sum()
        num_pred += pts.shape[0]
        num_gt += target.num
        if logits is not None:
            nearest_centres = centres[pred_to_gt]
            onehot = one_hot_targets(target.labels.to(pts.device)[pred_to_gt], logits.shape[-1])
            w = cls_w[None, :] * distance_weight(nearest_centres, pc_range)[:, None]
            focal_sum = focal_sum + (w * sigmoid_focal_loss(logits[b], onehot, alpha, gamma)).sum()
            num_focal += pts.shape[0]

    chamfer = chamfer_weight * (pred_sum / max(num_pred, 1) + gt_sum / max(num_gt, 1))
    focal = None if logits is None else focal_weight * focal_sum / max(num_focal, 1)
    return OccupancyLossResult(chamfer=chamfer, focal=focal, num_samples_without_gt=num_empty)
