"""The 2D obstacle map a planner reads (nav_msgs/OccupancyGrid fields) from a label grid: the
node publishes it (online/packing.py) and ``odg eval`` scores it (metrics/planner.py)."""
from __future__ import annotations

import numpy as np

from .classes import LABEL_SETS, OccLabels


def bev_fields(grid: np.ndarray, pc_range, voxel_size: float, min_z: float,
               max_z: float, labels: OccLabels = LABEL_SETS["nuscenes"],
               observed: np.ndarray | None = None) -> dict:
    """nav_msgs/OccupancyGrid fields (info + data) of a 2D obstacle map for planners.

    A cell (x, y) is occupied (100) if any voxel of its column whose centre height lies in
    [min_z, max_z] (metres, grid frame) has a label other than free or a drivable class
    (nuScenes: driveable_surface, Waymo: road), seen by a camera or not. Every other class
    (objects, but also sidewalk, terrain, other_flat) blocks: a planner must not drive there.
    Otherwise it is free (0) when a camera sees every voxel of the band from the column's
    highest drivable voxel up (the whole band where it has none), and unknown (-1) when not:
    behind an obstacle, outside every image (``observed`` bool [X, Y, Z]; None: every
    voxel counts as seen). OccupancyGrid is row-major with x along a row: data[y * width + x].
    """
    X, Y, Z = grid.shape
    z_centres = (np.arange(Z) + 0.5) * voxel_size + pc_range[2]
    band = (z_centres >= min_z) & (z_centres <= max_z)
    blocks = np.ones(256, dtype=bool)                  # label -> blocks a planner
    blocks[list(labels.passable())] = False
    column = grid[:, :, band]
    blocked = blocks[column]                           # [X, Y, Zb]; a table: ~5x np.isin
    occupied = blocked.any(axis=2).T                                 # [Y, X]
    data = np.where(occupied, 100, 0).astype(np.int8)
    if observed is not None:
        seen = observed[:, :, band]
        drivable = (column != labels.free_label) & ~blocked
        # from the highest drivable voxel up (argmax of the reversed band: its last one)
        Zb = int(band.sum())
        top = np.where(drivable.any(axis=2), Zb - 1 - drivable[:, :, ::-1].argmax(axis=2), -1)
        above = np.arange(Zb) >= top[:, :, None]
        unknown = (above & ~seen).any(axis=2).T                      # [Y, X]
        data[unknown & ~occupied] = -1
    return {
        "resolution": float(voxel_size), "width": X, "height": Y,
        "origin_position": (float(pc_range[0]), float(pc_range[1]), 0.0),
        "data": data.tobytes(),
    }
