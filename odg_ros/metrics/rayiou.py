"""RayIoU as SparseOcc computes it (``loaders/ray_metrics.py`` driving ``lib/dvr/dvr.cu``, which
OPUS ships unchanged), and the LiDAR origins it casts rays from.

Per sample, rays of the SparseOcc LiDAR pattern (``raycast.lidar_ray_directions``, 39 pitches x
360 azimuths, float32) are cast from each origin through the predicted and the GT grid (no
camera mask), traversed exactly as SparseOcc's caster does (``raycast``'s docstring). Each ray
reports the label of the voxel it stops in (the first non-free one; a free one if it leaves the
grid without a hit) and that voxel's exit distance, in float32 metres (float32 voxel units times
the float32 voxel size, as SparseOcc's float32 tensors hold them). Rays whose GT label is free
are dropped. Over the whole split, per class c and threshold t in {1, 2, 4} m, with the depth
error |d_pred - d_gt| taken in float32:

    gt_c   = rays whose GT label is c          pred_c = kept rays whose predicted label is c
    TP_c,t = rays with both labels c and |d_pred - d_gt| < t
    IoU_c,t = TP_c,t / (gt_c + pred_c - TP_c,t)      (NaN when gt_c = pred_c = 0)

RayIoU@t = nanmean over c of IoU_c,t; RayIoU = nanmean over all (c, t). A predicted ray that
hits nothing carries the free label and so counts for no class.

Origins (SparseOcc's EgoPoseDataset): the LiDAR position of every keyframe of the scene (past
and future), in the current keyframe's ego frame; those with |x| < 39 m and |y| < 39 m are kept
and, if more than 8 remain, 8 are taken at indices round(linspace(0, n - 1, 8)). As in
SparseOcc, another keyframe's LiDAR position is first expressed in the current LiDAR frame and
rounded to float32 there; the current keyframe's own origin is the LiDAR mounting translation
exactly (on nuScenes y = 0, which lies on the plane between voxel rows 99 and 100).
"""
from __future__ import annotations

from collections import defaultdict

import numpy as np

from ..classes import NUM_OCC_CLASSES
from .miou import check_labels
from .raycast import cast_rays, lidar_ray_directions, rays_in_voxel_units

THRESHOLDS = (1.0, 2.0, 4.0)          # metres
GRID_MIN = (-40.0, -40.0, -1.0)        # metres, the Occ3D grid corner in the ego frame
VOXEL_SIZE = 0.4                       # metres
MAX_ORIGINS = 8
ORIGIN_XY_LIMIT = 39.0                 # metres


class RayIoU:
    """Streaming RayIoU: ``add(pred, gt, origins)`` per sample, ``result()`` at the end.

    Keeps only per-class counts (gt_c, pred_c, TP_c,t), so a split never holds all grids.
    """

    def __init__(self, num_classes: int = NUM_OCC_CLASSES, thresholds=THRESHOLDS,
                 voxel_size: float = VOXEL_SIZE, grid_min=GRID_MIN, directions=None):
        """directions: unit ray directions [D, 3] cast from every origin, rounded to float32
        (default: the SparseOcc LiDAR pattern)."""
        self.num_classes = num_classes
        self.free_label = num_classes
        self.thresholds = tuple(float(t) for t in thresholds)
        self.voxel_size = float(voxel_size)
        self.grid_min = np.asarray(grid_min, dtype=np.float64)
        self.directions = (lidar_ray_directions() if directions is None
                           else np.asarray(directions, dtype=np.float32).reshape(-1, 3))
        self.gt_count = np.zeros(num_classes, dtype=np.int64)
        self.pred_count = np.zeros(num_classes, dtype=np.int64)
        self.tp_count = np.zeros((len(self.thresholds), num_classes), dtype=np.int64)
        self.samples = 0
        self.rays = 0

    def cast(self, grid: np.ndarray, origins: np.ndarray, other: np.ndarray | None = None):
        """Labels and depths (metres) of the first hits of all rays from ``origins`` [T, 3]
        (metres, ego frame) in ``grid`` (and ``other``, traversed together).

        Returns a list with one (label int64 [T*D], depth float32 [T*D]) per grid; rays are
        origin-major. A ray without a hit has label free and the depth where it leaves the grid;
        one that never enters the grid (an origin outside it) has voxel (0, 0, 0)'s label and
        depth -voxel_size, as in SparseOcc.
        """
        grids = [grid] if other is None else [grid, other]
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        num_dirs = self.directions.shape[0]
        start, end = rays_in_voxel_units(np.repeat(origins, num_dirs, axis=0),
                                         np.tile(self.directions, (origins.shape[0], 1)),
                                         self.grid_min, self.voxel_size)
        bits = np.zeros(grids[0].shape, dtype=np.uint8)
        for g, labels in enumerate(grids):
            bits |= (labels != self.free_label).astype(np.uint8) << g
        voxel, depth = cast_rays(bits, start, end, num_bits=len(grids))
        # SparseOcc writes the distance into a float32 tensor, then scales it in float32
        depth = depth.astype(np.float32) * np.float32(self.voxel_size)
        return [(labels.ravel()[voxel[g]].astype(np.int64), depth[g])
                for g, labels in enumerate(grids)]

    def add(self, pred: np.ndarray, gt: np.ndarray, origins: np.ndarray) -> None:
        """pred, gt: int [X, Y, Z] labels 0..C (C = free); origins: float [T, 3] LiDAR origins in
        metres in this sample's ego frame (``LidarOrigins``). T = 0 adds a sample with no rays."""
        pred = check_labels("prediction", pred, self.free_label)
        gt = check_labels("ground truth", gt, self.free_label)
        if pred.shape != gt.shape or pred.ndim != 3:
            raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} must be "
                             f"equal [X, Y, Z] grids")
        origins = np.asarray(origins, dtype=np.float64)
        if origins.ndim != 2 or origins.shape[1] != 3 or not np.isfinite(origins).all():
            raise ValueError(f"origins must be finite [T, 3] metres, got shape {origins.shape}")
        (pred_label, pred_depth), (gt_label, gt_depth) = self.cast(pred, origins, gt)
        self.add_rays(pred_label, pred_depth, gt_label, gt_depth)
        self.samples += 1

    def add_rays(self, pred_label, pred_depth, gt_label, gt_depth) -> None:
        """Count already cast rays (all [N]; labels 0..C, depths in metres, taken as float32
        as SparseOcc holds them). Rays whose GT label is free are dropped here."""
        pred_label, gt_label = np.asarray(pred_label), np.asarray(gt_label)
        pred_depth = np.asarray(pred_depth, dtype=np.float32)
        gt_depth = np.asarray(gt_depth, dtype=np.float32)
        keep = gt_label != self.free_label
        pred_label, gt_label = pred_label[keep], gt_label[keep]
        pred_depth, gt_depth = pred_depth[keep], gt_depth[keep]
        if np.isnan(pred_depth).any() or np.isnan(gt_depth).any():
            raise ValueError("ray depths must not be NaN")
        c = self.num_classes
        self.gt_count += np.bincount(gt_label, minlength=c + 1)[:c]
        self.pred_count += np.bincount(pred_label, minlength=c + 1)[:c]
        same = pred_label == gt_label  # gt is never free here, so neither is pred
        error = np.abs(pred_depth - gt_depth)  # float32, as in SparseOcc
        for j, threshold in enumerate(self.thresholds):
            tp = same & (error < threshold)
            self.tp_count[j] += np.bincount(gt_label[tp], minlength=c + 1)[:c]
        self.rays += int(keep.sum())

    def per_class_iou(self) -> np.ndarray:
        """float64 [len(thresholds), C] (NaN where a class is neither in GT nor predicted)."""
        union = self.gt_count + self.pred_count - self.tp_count
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(union > 0, self.tp_count / np.maximum(union, 1), np.nan)

    def result(self) -> dict:
        """Fractions (0..1, NaN allowed): "RayIoU", "RayIoU@<t>" per threshold, "per_class"
        [C] (mean over thresholds), "per_class_at" [len(thresholds), C], "samples", "rays"."""
        iou = self.per_class_iou()
        out = {}
        at = []
        for j, threshold in enumerate(self.thresholds):
            row = iou[j]
            at.append(float(np.nanmean(row)) if np.isfinite(row).any() else float("nan"))
            out[f"RayIoU@{threshold:g}"] = at[-1]
        # SparseOcc's nanmean over every (threshold, class) value: the mean of the three
        # RayIoU@t (every row has the same NaNs), summed in SparseOcc's order
        out["RayIoU"] = float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan")
        out["per_class"] = iou.mean(axis=0)  # NaN pattern is the same for every threshold
        out["per_class_at"] = iou
        out["samples"] = self.samples
        out["rays"] = self.rays
        return out


class LidarOrigins:
    """RayIoU ray origins of every keyframe of an infos list (see the module docstring).

    ``LidarOrigins(infos)(index)`` -> float64 [T, 3], 1 <= T <= 8 normally (0 only if no
    keyframe's LiDAR is within the limits), metres in the ego frame of ``infos[index]``.
    Keyframes of a scene are those with the same ``scene_token``, ordered by timestamp.
    """

    def __init__(self, infos: list[dict], max_origins: int = MAX_ORIGINS,
                 xy_limit: float = ORIGIN_XY_LIMIT):
        self.infos = infos
        self.max_origins = max_origins
        self.xy_limit = xy_limit
        scenes = defaultdict(list)
        for i, info in enumerate(infos):
            _pose(info, "ego_pose"), _pose(info, "lidar2ego")   # a bad pose fails here
            scenes[info["scene_token"]].append(i)
        self.scene_frames = {}
        for token, frames in scenes.items():
            frames.sort(key=lambda i: infos[i]["timestamp"])
            self.scene_frames[token] = frames

    def __call__(self, index: int) -> np.ndarray:
        info = self.infos[index]
        ego_from_lidar = _pose(info, "lidar2ego")
        lidar_from_global = np.linalg.inv(_pose(info, "ego_pose") @ ego_from_lidar)
        origins = []
        for i in self.scene_frames[info["scene_token"]]:
            if i == index:
                in_lidar = np.zeros(3, dtype=np.float32)
            else:
                global_from_lidar = _pose(self.infos[i], "ego_pose") @ _pose(self.infos[i],
                                                                             "lidar2ego")
                in_lidar = (lidar_from_global @ global_from_lidar)[:3, 3].astype(np.float32)
            origins.append(ego_from_lidar[:3] @ np.append(in_lidar.astype(np.float64), 1.0))
        origins = np.stack(origins)
        inside = (np.abs(origins[:, 0]) < self.xy_limit) & (np.abs(origins[:, 1]) < self.xy_limit)
        origins = origins[inside]
        if len(origins) > self.max_origins:
            pick = np.round(np.linspace(0, len(origins) - 1, self.max_origins)).astype(np.int64)
            origins = origins[pick]
        return origins


def lidar_origins(infos: list[dict], index: int) -> np.ndarray:
    """RayIoU origins [T, 3] (metres, ego frame) of keyframe ``index``. Builds the scene index
    each call; use ``LidarOrigins`` to score many keyframes."""
    return LidarOrigins(infos)(index)


def _pose(info: dict, key: str) -> np.ndarray:
    T = np.asarray(info[key], dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"keyframe {info.get('token', '?')}: {key} must be a finite 4x4 matrix")
    return T
