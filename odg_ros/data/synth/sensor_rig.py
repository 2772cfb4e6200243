"""The sensor rig of the synthetic car: the real nuScenes calibration and timing.

Camera and LiDAR extrinsics/intrinsics are the nuScenes ``calibrated_sensor`` records of
log n015-2018-07-24-11-22-45+0800 (scene-0061, v1.0-mini); intrinsics are for 1600 x 900
images and are scaled to the rendered size. Timing (docs/architecture.md sec. 2): LiDAR sweeps at 20 Hz
stamped at the end of the rotation, cameras at 12 Hz, each camera exposed when the rotating
LiDAR passes its view, i.e. 7..49.5 ms after the sweep start; keyframes at 2 Hz.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...geometry import make_transform
from ...nuscenes_cameras import CAMERA_NAMES

NUSCENES_IMAGE_HW = (900, 1600)

# name: (translation [m], rotation (w, x, y, z) T_ego_from_cam, intrinsics at 1600 x 900)
CAMERA_CALIBRATION = {
    "CAM_FRONT": (
        (1.70079118954, 0.0159456324149, 1.51095763913),
        (0.4998015430569128, -0.5030316162024876, 0.4997798114386805, -0.49737083824542755),
        ((1266.417203046554, 0.0, 816.2670197447984), (0.0, 1266.417203046554, 491.50706579294757),
         (0.0, 0.0, 1.0))),
    "CAM_FRONT_RIGHT": (
        (1.5508477543, -0.493404796419, 1.49574800619),
        (0.2060347966337182, -0.2026940577919598, 0.6824507824531167, -0.6713610884174485),
        ((1260.8474446004698, 0.0, 807.968244525554), (0.0, 1260.8474446004698, 495.3344268742088),
         (0.0, 0.0, 1.0))),
    "CAM_FRONT_LEFT": (
        (1.52387798135, 0.494631336551, 1.50932822144),
        (0.6757265034669446, -0.6736266522251881, 0.21214015046209478, -0.21122827103904068),
        ((1272.5979470598488, 0.0, 826.6154927353808), (0.0, 1272.5979470598488, 479.75165386361925),
         (0.0, 0.0, 1.0))),
    "CAM_BACK": (
        (0.0283260309358, 0.00345136761476, 1.57910346144),
        (0.5037872666382278, -0.49740249788611096, -0.4941850223835201, 0.5045496097725578),
        ((809.2209905677063, 0.0, 829.2196003259838), (0.0, 809.2209905677063, 481.77842384512485),
         (0.0, 0.0, 1.0))),
    "CAM_BACK_LEFT": (
        (1.03569100218, 0.484795032713, 1.59097014818),
        (0.6924185592174665, -0.7031619420114925, -0.11648342771943819, 0.11203317912370753),
        ((1256.7414812095406, 0.0, 792.1125740759628), (0.0, 1256.7414812095406, 492.7757465151356),
         (0.0, 0.0, 1.0))),
    "CAM_BACK_RIGHT": (
        (1.0148780988, -0.480568219723, 1.56239545128),
        (0.12280980120078765, -0.132400842670559, -0.7004305821388234, 0.690496031265798),
        ((1259.5137405846733, 0.0, 807.2529053838625), (0.0, 1259.5137405846733, 501.19579884916527),
         (0.0, 0.0, 1.0))),
}
LIDAR_CALIBRATION = (
    (0.943713, 0.0, 1.84023),
    (0.7077955119163518, -0.006492242056004365, 0.010646214713995808, -0.7063073142877817),
)

# Exposure time of each camera after the LiDAR sweep start, seconds (from nuScenes stamps:
# the LiDAR turns clockwise seen from above, front-left first, back-left last).
CAMERA_DELAY_S = {
    "CAM_FRONT_LEFT": 0.0069, "CAM_FRONT": 0.0145, "CAM_FRONT_RIGHT": 0.0224,
    "CAM_BACK_RIGHT": 0.0299, "CAM_BACK": 0.0396, "CAM_BACK_LEFT": 0.0495,
}
LIDAR_HZ = 20
CAMERA_HZ = 12
KEYFRAME_HZ = 2
SWEEPS_PER_KEYFRAME = LIDAR_HZ // KEYFRAME_HZ      # 10 LiDAR sweeps per keyframe
CAMERA_SETS_PER_KEYFRAME = CAMERA_HZ // KEYFRAME_HZ  # 6 camera sets per keyframe

# Velodyne HDL-32E (the nuScenes LIDAR_TOP): 32 beams from -30.67 to +10.67 degrees.
LIDAR_ELEVATIONS_DEG = np.linspace(-30.67, 10.67, 32)
LIDAR_AZIMUTHS = 1084  # columns per rotation (nuScenes sweeps have ~34k points)
LIDAR_MAX_RANGE = 80.0
LIDAR_MIN_RANGE = 1.0


@dataclass(frozen=True)
class Camera:
    name: str
    T_ego_from_cam: np.ndarray  # 4x4
    intrinsics: np.ndarray      # 3x3 for image_hw
    image_hw: tuple


def cameras(image_hw=(900, 1600)) -> list[Camera]:
    """The six cameras in CAMERA_NAMES order with intrinsics scaled to ``image_hw``."""
    h, w = int(image_hw[0]), int(image_hw[1])
    if h < 8 or w < 8:
        raise ValueError(f"image size {image_hw} too small")
    out = []
    for name in CAMERA_NAMES:
        t, q, K = CAMERA_CALIBRATION[name]
        K = np.array(K, dtype=np.float64)
        K[0] *= w / NUSCENES_IMAGE_HW[1]
        K[1] *= h / NUSCENES_IMAGE_HW[0]
        out.append(Camera(name, make_transform(q, t), K, (h, w)))
    return out


def lidar_T_ego_from_lidar() -> np.ndarray:
    return make_transform(LIDAR_CALIBRATION[1], LIDAR_CALIBRATION[0])
