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
import yaml

from ...geometry import make_transform
from ...nuscenes_cameras import CAMERA_NAMES
from ...resources import resource_path

NUSCENES_IMAGE_HW = (900, 1600)


def _shipped_cameras() -> dict:
    """name -> (translation [m], rotation (w, x, y, z) T_ego_from_cam, intrinsics at 1600 x
    900): the node's default rig file, which holds these very records."""
    rig = yaml.safe_load(resource_path("config/rig_nuscenes.yaml").read_text())
    return {name: (camera["sensor2ego"]["translation"], camera["sensor2ego"]["rotation"],
                   camera["intrinsics"]) for name, camera in rig["cameras"].items()}


CAMERA_CALIBRATION = _shipped_cameras()
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
