"""Prediction arrays -> the field values of the output messages (no ROS types here).

Large arrays become ``bytes`` (``ndarray.tobytes()``) or flat uint8 arrays, never Python
lists: copying them into a uint8[] / int8[] message field is a memcpy, a list is ~100x
slower (docs/architecture.md sec. 7). The node copies these values into odg_ros_msgs /
sensor_msgs / nav_msgs messages.
"""
from __future__ import annotations

import numpy as np

from ..classes import BOX_CLASSES, LABEL_SETS, OCC_CLASSES, OCC_COLORS, OccLabels
from ..rotation import yaw_to_quaternion

NUSCENES_LABELS = LABEL_SETS["nuscenes"]

# sensor_msgs/PointField datatypes
POINTFIELD_UINT8 = 2
POINTFIELD_FLOAT32 = 7

# One PointCloud2 point: x, y, z float32 + label uint8, padded to 16 bytes (aligned rows).
CLOUD_DTYPE = np.dtype({"names": ["x", "y", "z", "label"],
                        "formats": ["<f4", "<f4", "<f4", "u1"],
                        "offsets": [0, 4, 8, 12], "itemsize": 16})


def voxel_grid_fields(grid: np.ndarray, confidence: np.ndarray | None, pc_range,
                      voxel_size: float, labels: OccLabels = NUSCENES_LABELS,
                      observed: np.ndarray | None = None) -> dict:
    """odg_ros_msgs/SemanticVoxelGrid fields (all but the header); labels, confidence and
    observed flat uint8 [X*Y*Z] in the grid's C order (views of the arrays given where
    contiguous).

    grid uint8 [X, Y, Z] (labels.free_label = free); confidence uint8 [X, Y, Z] or None;
    labels: the model's label set (ModelConfig.labels), which names the classes; observed
    bool [X, Y, Z] (a camera sees the voxel) or None (the field stays empty).
    """
    if grid.dtype != np.uint8 or grid.ndim != 3:
        raise ValueError(f"grid must be uint8 [X, Y, Z], got {grid.dtype} {grid.shape}")
    for name, other in (("confidence", confidence), ("observed", observed)):
        if other is not None and other.shape != grid.shape:
            raise ValueError(f"{name} {other.shape} != grid {grid.shape}")
    X, Y, Z = grid.shape
    return {
        "origin_position": tuple(float(v) for v in pc_range[:3]),   # minimum corner
        "resolution": float(voxel_size),
        "size_x": X, "size_y": Y, "size_z": Z,
        "memory_order": "xyz_c",
        "free_label": labels.free_label,
        "unknown_label": 255,
        # flat uint8 views (no copy): the node copies them into its message
        "labels": np.ascontiguousarray(grid).reshape(-1),
        "confidence": np.zeros(0, np.uint8) if confidence is None else
        np.ascontiguousarray(confidence, dtype=np.uint8).reshape(-1),
        "observed": np.zeros(0, np.uint8) if observed is None else
        np.ascontiguousarray(observed).reshape(-1).view(np.uint8),
        "class_names": list(labels.names),
    }


def cloud_fields(grid: np.ndarray, pc_range, voxel_size: float,
                 labels: OccLabels = NUSCENES_LABELS,
                 observed: np.ndarray | None = None) -> dict:
    """sensor_msgs/PointCloud2 fields (all but the header) of the occupied voxel centres:
    x y z float32, label uint8, and with ``observed`` (bool [X, Y, Z]) an observed uint8
    (1: a camera sees the voxel, 0: predicted where no camera sees).

    'fields' is a list of (name, offset, datatype, count) for sensor_msgs/PointField.
    """
    X, Y, Z = grid.shape
    flat = np.ascontiguousarray(grid).reshape(-1)
    occupied = np.flatnonzero(flat != labels.free_label)                # C order
    # per-axis centre tables and index arithmetic: ~3x cheaper than argwhere + [M, 3] maths
    ix, rest = np.divmod(occupied, Y * Z)
    iy, iz = np.divmod(rest, Z)
    origin = np.asarray(pc_range[:3], dtype=np.float64)
    points = np.zeros((len(occupied), CLOUD_DTYPE.itemsize // 4), dtype="<f4")
    for axis, (index, size) in enumerate(((ix, X), (iy, Y), (iz, Z))):
        centres = ((np.arange(size) + 0.5) * voxel_size + origin[axis]).astype(np.float32)
        points[:, axis] = centres[index]
    points.view(np.uint8)[:, 12] = flat[occupied]                   # label byte, then padding
    fields = [("x", 0, POINTFIELD_FLOAT32, 1), ("y", 4, POINTFIELD_FLOAT32, 1),
              ("z", 8, POINTFIELD_FLOAT32, 1), ("label", 12, POINTFIELD_UINT8, 1)]
    if observed is not None:
        points.view(np.uint8)[:, 13] = np.ascontiguousarray(observed).reshape(-1)[occupied]
        fields.append(("observed", 13, POINTFIELD_UINT8, 1))
    return {
        "height": 1, "width": len(points),
        "fields": fields,
        "is_bigendian": False,
        "point_step": CLOUD_DTYPE.itemsize,
        "row_step": CLOUD_DTYPE.itemsize * len(points),
        "data": points.tobytes(),
        "is_dense": True,
    }


def object_fields(box: dict) -> dict:
    """odg_ros_msgs/DynamicObject fields from one network.postprocess.box_list entry.

    box_list sizes are (w, l, h) with l along the heading; the message wants
    size.x = length, size.y = width, size.z = height.
    """
    w, l, h = (float(v) for v in box["size"])
    return {
        "class_id": int(box["label"]), "class_name": str(box["class_name"]),
        "score": float(box["score"]),
        "position": tuple(float(v) for v in box["center"]),
        "orientation": yaw_to_quaternion(float(box["yaw"])),
        "size": (l, w, h),
        "velocity": (float(box["velocity"][0]), float(box["velocity"][1]), 0.0),
    }


def box_color(label: int) -> tuple[float, float, float]:
    """RGB in [0, 1] of a box class (the colour of the same occupancy class)."""
    occ_label = OCC_CLASSES.index(BOX_CLASSES[label])
    return tuple(c / 255.0 for c in OCC_COLORS[occ_label])
