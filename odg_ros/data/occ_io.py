"""Occupancy ground truth on disk -> the common triple (semantics, mask_lidar, mask_camera).

Both benchmarks use the same grid: [-40, -40, -1, 40, 40, 5.4] m, 200 x 200 x 16 voxels of
0.4 m, indexed [x, y, z] in the keyframe's ego frame (docs/architecture.md sec. 1).

Occ3D-nuScenes (``gts/<scene_name>/<sample_token>/labels.npz``)::

    semantics   uint8 [200, 200, 16]  0..16 classes, 17 free   -> semantics (as is)
    mask_lidar  uint8 {0, 1}          voxel observed by LiDAR  -> mask_lidar (bool)
    mask_camera uint8 {0, 1}          voxel visible in cameras -> mask_camera (bool)

Occ3D-Waymo (``<split>/<scene:03d>/<frame:03d>_04.npz``, the 0.4 m release)::

    voxel_label        uint8  0..14 classes (0 = general object), free stored as 23 in the
                                 released files (their README: "labels 0 - 14, 23")
                                 -> semantics, the file's free label replaced by ``free_label``
                                    (default classes.WAYMO_FREE_LABEL = 15)
    origin_voxel_state           LiDAR observation state       -> mask_lidar  = state != 0
    final_voxel_state            camera observation state      -> mask_camera = state != 0 AND
    infov                        inside the 5 cameras' frusta     infov != 0
                                 (Waymo has no rear camera, so visibility needs both, as the
                                  Occ3D-Waymo evaluations do)

Files whose free voxels already carry ``free_label`` load the same way. Any other label
outside 0..14 is an error, never silently kept.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..classes import FREE_LABEL, WAYMO_FREE_LABEL

GRID_SHAPE = (200, 200, 16)
WAYMO_FILE_FREE_LABEL = 23   # free label in the released Occ3D-Waymo files
NUM_WAYMO_CLASSES = 15       # 0..14


def _read_npz(path, keys) -> dict[str, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"occupancy GT file not found: {path}")
    with np.load(path, allow_pickle=False) as data:
        missing = [k for k in keys if k not in data.files]
        if missing:
            raise ValueError(f"{path}: missing keys {missing} (has {sorted(data.files)})")
        arrays = {k: np.asarray(data[k]) for k in keys}
    shapes = {k: a.shape for k, a in arrays.items()}
    if len(set(shapes.values())) != 1 or len(next(iter(shapes.values()))) != 3:
        raise ValueError(f"{path}: expected equal 3-D arrays, got shapes {shapes}")
    return arrays


def _check_grid(path, shape, grid_shape) -> None:
    if grid_shape is not None and tuple(shape) != tuple(grid_shape):
        raise ValueError(f"{path}: grid {tuple(shape)} does not match the model grid "
                         f"{tuple(grid_shape)}")


def load_occ3d_nuscenes(path, grid_shape=GRID_SHAPE):
    """Occ3D-nuScenes ``labels.npz`` -> (semantics uint8 [X,Y,Z] with 17 = free,
    mask_lidar bool [X,Y,Z], mask_camera bool [X,Y,Z])."""
    a = _read_npz(path, ("semantics", "mask_lidar", "mask_camera"))
    semantics = a["semantics"]
    _check_grid(path, semantics.shape, grid_shape)
    if semantics.size and (semantics.min() < 0 or semantics.max() > FREE_LABEL):
        raise ValueError(f"{path}: semantics outside 0..{FREE_LABEL} "
                         f"(min {semantics.min()}, max {semantics.max()})")
    return (semantics.astype(np.uint8), a["mask_lidar"] != 0, a["mask_camera"] != 0)


def load_occ3d_waymo(path, free_label: int = WAYMO_FREE_LABEL,
                     file_free_label: int = WAYMO_FILE_FREE_LABEL, grid_shape=GRID_SHAPE):
    """Occ3D-Waymo ``*_04.npz`` -> (semantics uint8 [X,Y,Z] with ``free_label`` = free,
    mask_lidar bool, mask_camera bool); the mapping is in the module docstring."""
    a = _read_npz(path, ("voxel_label", "origin_voxel_state", "final_voxel_state", "infov"))
    labels = a["voxel_label"].astype(np.int64)
    _check_grid(path, labels.shape, grid_shape)
    free = (labels == file_free_label) | (labels == free_label)
    bad = ~free & ((labels < 0) | (labels >= NUM_WAYMO_CLASSES))
    if bad.any():
        raise ValueError(f"{path}: voxel_label has values {np.unique(labels[bad])[:10].tolist()} "
                         f"outside 0..{NUM_WAYMO_CLASSES - 1} and free ({file_free_label})")
    semantics = np.where(free, free_label, labels).astype(np.uint8)
    mask_lidar = a["origin_voxel_state"] != 0
    mask_camera = (a["final_voxel_state"] != 0) & (a["infov"] != 0)
    return semantics, mask_lidar, mask_camera


def load_occ(path, dataset: str = "nuscenes", grid_shape=GRID_SHAPE):
    """The loader for ``dataset`` ('nuscenes' | 'waymo'), each with its default free label."""
    if dataset == "nuscenes":
        return load_occ3d_nuscenes(path, grid_shape=grid_shape)
    if dataset == "waymo":
        return load_occ3d_waymo(path, grid_shape=grid_shape)
    raise ValueError(f"unknown dataset {dataset!r} (expected 'nuscenes' or 'waymo')")


def free_label_of(dataset: str) -> int:
    """The free label of the triple ``load_occ`` returns for ``dataset``."""
    if dataset == "nuscenes":
        return FREE_LABEL
    if dataset == "waymo":
        return WAYMO_FREE_LABEL
    raise ValueError(f"unknown dataset {dataset!r} (expected 'nuscenes' or 'waymo')")


def empty_occ(dataset: str = "nuscenes", grid_shape=GRID_SHAPE):
    """All-free semantics and all-False masks, for keyframes without GT."""
    semantics = np.full(grid_shape, free_label_of(dataset), dtype=np.uint8)
    mask = np.zeros(grid_shape, dtype=bool)
    return semantics, mask, mask.copy()

