"""Inference outputs: the Occ3D grid and the box list, with static shapes and no host sync.

Grid: the last layer's points with max sigmoid score > threshold that lie within 3 m of
their query's centroid are voxelised; scores are averaged per voxel; label = argmax;
everything else is free (``free_label``, by default the class count: 17 on Occ3D-nuScenes,
15 on Occ3D-Waymo). The points are grouped by voxel with a sort (no ``unique``: its output
size would need a host read), dropped points go to one dummy voxel past the grid, and only
the P = Q*K per-point segments carry class scores (no dense class volume).
Boxes: one per dynamic query, score = max box class probability; on the device a fixed
top-D tensor sorted by score with a valid mask, turned into dicts on the host.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..classes import BOX_CLASSES
from ..model_config import ModelConfig
from .outputs import ODGOutput


@torch.no_grad()
def occupancy_grid(output: ODGOutput, cfg: ModelConfig, free_label: int | None = None):
    """-> labels uint8 [B, X, Y, Z] (``free_label``, default cfg.num_classes, where empty),
    confidence uint8 [B, X, Y, Z] (0..255)."""
    layer = output.last
    labels, confidence = voxelise(layer.means, layer.logits, cfg,
                                  cfg.num_classes if free_label is None else free_label)
    B = labels.shape[0]
    return labels.view(B, *cfg.grid_shape), confidence.view(B, *cfg.grid_shape)


def point_voxels(means: torch.Tensor, scores: torch.Tensor, cfg: ModelConfig):
    """means [..., K, 3], scores [..., K, C] (sigmoid) -> which points the grid keeps (score
    above the threshold, within max_distance_to_centroid of their query's centroid, finite,
    inside the grid) [..., K] and each point's flat voxel index [..., K] (X*Y*Z, the dummy
    voxel, where not kept)."""
    passing, distance = _passing_and_distance(means, scores.max(dim=-1).values, cfg)
    near = distance <= cfg.max_distance_to_centroid
    return _grid_voxels(means, passing & near & torch.isfinite(means).all(-1), cfg)


def stray_voxels(means: torch.Tensor, logits: torch.Tensor, cfg: ModelConfig) -> torch.Tensor:
    """means [B, Q, K, 3], logits [B, Q, K, C] -> bool [B, X*Y*Z]: the voxels holding a point
    whose score passes the threshold but that the grid drops for lying farther than
    max_distance_to_centroid from its query's centroid. The model put something there: in
    dense traffic such a voxel the grid calls free is truly occupied about half the time, so
    the visibility lets it hide what lies behind it (network/visibility.py)."""
    means = means.float()
    B = means.shape[0]
    # the sigmoid of the top logit: the top score exactly (sigmoid is monotone)
    passing, distance = _passing_and_distance(means, logits.float().amax(dim=-1).sigmoid(),
                                              cfg)
    # (a query with a NaN point has a NaN centroid: none of its points is far, nor near)
    far = distance > cfg.max_distance_to_centroid
    _, flat = _grid_voxels(means, passing & far & torch.isfinite(means).all(-1), cfg)
    cells = math.prod(cfg.grid_shape)
    out = torch.zeros((B, cells + 1), dtype=torch.uint8, device=means.device)
    out.scatter_(1, flat.view(B, -1), 1)
    return out[:, :cells].bool()


def _passing_and_distance(means: torch.Tensor, top_score: torch.Tensor, cfg: ModelConfig):
    """Per point: whether its top score passes the threshold, and its distance from its
    query's centroid."""
    centroid = means.mean(dim=-2, keepdim=True)
    return top_score > cfg.score_threshold, (means - centroid).norm(dim=-1)


def _grid_voxels(means: torch.Tensor, chosen: torch.Tensor, cfg: ModelConfig):
    """The ``chosen`` points that lie inside the grid [..., K] and each point's flat voxel
    index [..., K] (X*Y*Z, the dummy voxel, for the others)."""
    X, Y, Z = cfg.grid_shape
    # per axis with Python scalars: a constant tensor would be a host-to-device copy
    index = []
    for axis, size in enumerate((X, Y, Z)):
        i = torch.floor((means[..., axis] - cfg.pc_range[axis]) / cfg.voxel_size)
        chosen = chosen & (i >= 0) & (i < size)
        index.append(torch.where(chosen, i, torch.zeros_like(i)).long())
    flat = torch.where(chosen, (index[0] * Y + index[1]) * Z + index[2],
                       torch.full_like(index[0], X * Y * Z))
    return chosen, flat


def voxelise(means: torch.Tensor, logits: torch.Tensor, cfg: ModelConfig, free_label: int):
    """means [B, Q, K, 3], logits [B, Q, K, C] -> labels, confidence uint8 [B, X*Y*Z]."""
    means, scores = means.float(), logits.float().sigmoid()
    B, Q, K, C = scores.shape
    cells = math.prod(cfg.grid_shape)                  # index ``cells``: the dummy voxel
    keep, flat = point_voxels(means, scores, cfg)
    flat = flat.view(B, Q * K)
    scores = torch.where(keep.unsqueeze(-1), scores, torch.zeros_like(scores)).view(B, Q * K, C)
    # a stable sort keeps each voxel's points in query order: the same summation order as
    # adding them up point by point
    voxel, order = torch.sort(flat, dim=1, stable=True)
    starts = torch.ones_like(voxel, dtype=torch.bool)
    starts[:, 1:] = voxel[:, 1:] != voxel[:, :-1]
    segment = starts.long().cumsum(dim=1) - 1                         # [B, P] in 0..P-1
    # the points' score rows in voxel order: rows picked by index_select (gather with an
    # expanded index copies element by element on the CPU, ~40x slower)
    rows = order + torch.arange(B, device=order.device).unsqueeze(1) * (Q * K)
    sorted_scores = scores.flatten(0, 1).index_select(0, rows.flatten()).view(B, Q * K, C)
    summed = torch.zeros_like(scores).scatter_add_(
        1, segment.unsqueeze(-1).expand(-1, -1, C), sorted_scores)
    counts = torch.zeros(B, Q * K, device=means.device).scatter_add_(
        1, segment, torch.ones_like(voxel, dtype=torch.float32))
    segment_voxel = torch.full_like(voxel, cells).scatter_(1, segment, voxel)
    top, label = (summed / counts.clamp(min=1).unsqueeze(-1)).max(dim=-1)
    labels = torch.full((B, cells + 1), free_label, dtype=torch.uint8, device=means.device)
    labels.scatter_(1, segment_voxel, label.to(torch.uint8))
    confidence = torch.zeros((B, cells + 1), dtype=torch.uint8, device=means.device)
    confidence.scatter_(1, segment_voxel,
                        (top * 255).round().clamp(0, 255).to(torch.uint8))
    return labels[:, :cells], confidence[:, :cells]


def decode_box_code(code: torch.Tensor) -> torch.Tensor:
    """[..., 10] code -> [..., 9] (cx, cy, cz, w, l, h, yaw, vx, vy)."""
    size = code[..., 3:6].clamp(max=math.log(50.0)).exp()  # no 1e30 m boxes from a bad logit
    yaw = torch.atan2(code[..., 6], code[..., 7])
    return torch.cat([code[..., :3], size, yaw.unsqueeze(-1), code[..., 8:10]], dim=-1)


def ranked_boxes(boxes: torch.Tensor, box_logits: torch.Tensor, threshold: float):
    """boxes [B, D, 10] codes, box_logits [B, D, C_box] -> every query's box sorted by score,
    the ones that pass first: boxes [B, D, 9] (decoded), score [B, D], label [B, D],
    valid [B, D] (score > threshold and a finite code and box)."""
    score, label = box_logits.float().sigmoid().max(dim=-1)
    decoded = decode_box_code(boxes.float())
    # the code, not only the decoded box: the size clamp would turn an inf code into 50 m
    valid = (score > threshold) & torch.isfinite(boxes.float()).all(-1) & \
        torch.isfinite(decoded).all(-1)
    key = torch.where(valid, score, torch.full_like(score, -1.0))    # scores are in [0, 1]
    order = torch.argsort(key, dim=1, descending=True, stable=True)
    return (decoded.gather(1, order.unsqueeze(-1).expand(-1, -1, decoded.shape[-1])),
            score.gather(1, order), label.gather(1, order), valid.gather(1, order))


def box_dicts(boxes: np.ndarray, score: np.ndarray, label: np.ndarray,
              valid: np.ndarray) -> list[dict]:
    """One sample of ``ranked_boxes`` on the host -> list of dicts {label, class_name, score,
    center, size (w, l, h), yaw, velocity}, the valid ones, by score."""
    return [{"label": int(label[i]), "class_name": BOX_CLASSES[int(label[i])],
             "score": float(score[i]), "center": boxes[i, :3].tolist(),
             "size": boxes[i, 3:6].tolist(), "yaw": float(boxes[i, 6]),
             "velocity": boxes[i, 7:9].tolist()} for i in np.flatnonzero(valid)]


@torch.no_grad()
def box_list(output: ODGOutput, cfg: ModelConfig, score_threshold: float | None = None):
    """-> per sample a list of dicts (``box_dicts``), sorted by score, for dynamic queries
    whose score passes the threshold."""
    threshold = cfg.box_score_threshold if score_threshold is None else score_threshold
    layer = output.last
    if layer.boxes is None:
        return [[] for _ in range(layer.means.shape[0])]
    ranked = [t.cpu().numpy() for t in ranked_boxes(layer.boxes, layer.box_logits, threshold)]
    return [box_dicts(*(t[b] for t in ranked)) for b in range(ranked[0].shape[0])]
