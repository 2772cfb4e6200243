"""LiDAR sweeps and labels on disk, and their projection into the cameras (render targets).

nuScenes files:
* ``samples/LIDAR_TOP/*.pcd.bin``: float32 records of 5 values (x, y, z, intensity, ring index),
  x, y, z in metres in the LiDAR frame.
* ``lidarseg/<version>/<lidar sample_data token>_lidarseg.bin``: one uint8 nuScenes-lidarseg
  label per point of the matching ``.pcd.bin``, same order.

Render targets (paper Eq. 6 supervision, docs/architecture.md sec. 5): every labelled LiDAR point is
projected into each current-frame camera with that camera's ``ego2img``; a point is kept when it
is at least ``min_depth`` in front of the camera and lands inside the part of the network input
that shows the image (bottom padding excluded). Per pixel (floor(u), floor(v)) only the nearest
point is kept, so a target never sees through a closer surface.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

POINT_DIMS = 5
# The nuScenes devkit drops points closer than 1 m to the camera when it maps a sweep into an
# image (they are on the ego vehicle or too close for a stable projection); we do the same.
MIN_DEPTH = 1.0


def load_points(path) -> np.ndarray:
    """``.pcd.bin`` -> float32 [P, 5] (x, y, z, intensity, ring) in the LiDAR frame."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"LiDAR file not found: {path}")
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % POINT_DIMS:
        raise ValueError(f"{path}: {raw.size} float32 values, not a multiple of {POINT_DIMS}")
    points = raw.reshape(-1, POINT_DIMS)
    if not np.all(np.isfinite(points[:, :3])):
        raise ValueError(f"{path}: non-finite point coordinates")
    return points


def load_lidarseg(path, num_points: int) -> np.ndarray:
    """``*_lidarseg.bin`` -> uint8 [P] nuScenes-lidarseg labels; P must match the sweep."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"lidarseg file not found: {path}")
    labels = np.fromfile(path, dtype=np.uint8)
    if labels.size != num_points:
        raise ValueError(f"{path}: {labels.size} labels for {num_points} points")
    return labels


def transform_points(T, points_xyz) -> np.ndarray:
    """Apply a 4x4 rigid transform to [P, 3] points (float64 result)."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points_xyz, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def lidar_render_targets(points_ego, labels, ego2img, image_hw, valid_heights=None,
                       num_classes: int = 17, min_depth: float = MIN_DEPTH) -> list[np.ndarray]:
    """Render targets of one frame.

    points_ego    [P, 3] points in the frame's ego coordinates (metres)
    labels        [P] occupancy labels; points whose label is not a class (>= num_classes:
                  free / ignore) are dropped, they have no class to supervise
    ego2img       [N, 4, 4] ego -> (u*d, v*d, d, 1) of the network input (geometry.ego_to_image)
    image_hw      (H, W) of the network input
    valid_heights optional [N] rows of each input image that show the camera image (the rest
                  is bottom padding); default H
    returns       N float32 arrays [P_n, 4] = (u, v, depth, label): u, v the exact projected
                  input-pixel coordinates, at most one point per pixel (the nearest)
    """
    points_ego = np.asarray(points_ego, dtype=np.float64).reshape(-1, 3)
    labels = np.asarray(labels).reshape(-1)
    ego2img = np.asarray(ego2img, dtype=np.float64)
    if labels.shape[0] != points_ego.shape[0]:
        raise ValueError(f"{labels.shape[0]} labels for {points_ego.shape[0]} points")
    H, W = image_hw
    num_cams = ego2img.shape[0]
    valid_heights = [H] * num_cams if valid_heights is None else list(valid_heights)
    keep_class = labels.astype(np.int64) < num_classes
    points_ego, labels = points_ego[keep_class], labels[keep_class]
    homogeneous = np.concatenate([points_ego, np.ones((len(points_ego), 1))], axis=1)
    targets = []
    for n in range(num_cams):
        projected = homogeneous @ ego2img[n].T
        depth = projected[:, 2]
        in_front = depth >= min_depth
        # float32 before the bounds test, so the stored coordinates stay inside the image
        u = (projected[in_front, 0] / depth[in_front]).astype(np.float32)
        v = (projected[in_front, 1] / depth[in_front]).astype(np.float32)
        d, lab = depth[in_front], labels[in_front]
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < min(H, valid_heights[n]))
        u, v, d, lab = u[inside], v[inside], d[inside], lab[inside]
        # nearest point per pixel: sort by depth, keep each pixel's first occurrence
        order = np.argsort(d, kind="stable")
        pixel = np.floor(v[order]).astype(np.int64) * W + np.floor(u[order]).astype(np.int64)
        _, first = np.unique(pixel, return_index=True)
        chosen = order[first]
        targets.append(np.stack([u[chosen], v[chosen], d[chosen], lab[chosen].astype(np.float64)],
                                axis=1).astype(np.float32))
    return targets
