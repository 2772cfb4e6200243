"""The nuScenes camera rig: its camera names in order (the one place that order is written:
batches, bags, the node and the synthetic world read it here), and a surround ring of
cameras at its headings for benchmarks and tests when no calibration is at hand: six cameras
(front, front-right, front-left, back, back-left, back-right), 1.5 m high, looking
horizontally, with the nuScenes ~70 degree horizontal field of view scaled to the network
input. Importing this module does not import torch (the bag tools rely on that)."""
from __future__ import annotations

import math

import numpy as np

from .geometry import ego_to_image

CAMERA_NAMES = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT",
                "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
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
    import torch
    K, T_ego_cam = ring_cameras(image_hw, num_cams)
    mats = np.stack([ego_to_image(k, t) for k, t in zip(K, T_ego_cam)])
    return torch.from_numpy(mats).float().expand(batch, num_frames, -1, -1, -1).clone()


def online_inputs(cfg, frames: int, device, seed: int = 0):
    """Random current images [1, N, 3, H, W] and the geometry of ``frames`` frames of a car
    driving 10 m/s straight ahead with the ring rig, for preset ``cfg`` (a ModelConfig)."""
    import torch
    g = torch.Generator().manual_seed(seed)
    H, W = cfg.image_size
    images = torch.randn(1, cfg.num_cams, 3, H, W, generator=g).to(device)
    ego2img = ring_ego2img(cfg.image_size, frames, cfg.num_cams).to(device)
    time_delta = torch.arange(frames, dtype=torch.float32, device=device)[None] * 0.5
    ego_warp = torch.eye(4, device=device).repeat(1, frames, 1, 1)
    ego_warp[0, :, 0, 3] = 10.0 * time_delta[0]  # the past ego was behind: x_past = x + v dt
    return images, ego2img, ego_warp, time_delta
