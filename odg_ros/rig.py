"""A surround camera ring for benchmarks and tests when no calibration is at hand: six
cameras at the nuScenes headings (front, front-right, front-left, back, back-left,
back-right), 1.5 m high, looking horizontally, with the nuScenes ~70 degree horizontal
field of view scaled to the network input."""
from __future__ import annotations

import math

import numpy as np
import torch

from .geometry import ego_to_image

YAWS_DEG = (0.0, -55.0, 55.0, 180.0, 110.0, -110.0)


def ring_cameras(image_hw, num_cams: int = 6):
    """-> intrinsics [N, 3, 3], T_ego_from_cam [N, 4, 4] (NumPy float64)."""
    H, W = image_hw
    focal = (W / 2) / math.tan(math.radians(70.0) / 2)
    K = np.array([[focal, 0, W / 2], [0, focal, H / 2], [0, 0, 1.0]])
    # camera axes (x right, y down, z forward) expressed in ego axes (x fwd, y left, z up)
    cam_to_ego_axes = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=np.float64)
    intrinsics, extrinsics = [], []
    for yaw in YAWS_DEG[:num_cams]:
        c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        T = np.eye(4)
        T[:3, :3] = Rz @ cam_to_ego_axes
        T[:3, 3] = [1.0 * c, 1.0 * s, 1.5]
        intrinsics.append(K.copy())
        extrinsics.append(T)
    return np.stack(intrinsics), np.stack(extrinsics)


def ring_ego2img(image_hw, num_frames: int, num_cams: int = 6, batch: int = 1):
    """ego2img [B, T, N, 4, 4] (float32 torch) of a static ring rig."""
    K, T_ego_cam = ring_cameras(image_hw, num_cams)
    mats = np.stack([ego_to_image(k, t) for k, t in zip(K, T_ego_cam)])
    return torch.from_numpy(mats).float().expand(batch, num_frames, -1, -1, -1).clone()
