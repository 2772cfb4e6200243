"""Camera calibration online: rig files, CameraInfo checks and the ego->image matrices of a set.

A rig file (``config/rig_nuscenes.yaml``) gives per camera its frame id, original image
size, intrinsics and ``sensor2ego`` (T_ego_from_cam). Online, the intrinsics and size come
from each camera's CameraInfo; the extrinsics from the rig file or TF.

The six images of a set are taken at slightly different times (up to ~42 ms apart on
nuScenes) while the car moves, so, as in the nuScenes infos, each camera is placed with the
ego pose at its own stamp and the set's ego frame is the ego at the reference stamp::

    ego2img[n] = [K'_n 0; 0 1] @ inv(sensor2ego_n) @ inv(P(t_n)) @ P(t_ref)

with P = T_global_from_ego and K' the network-input intrinsics (geometry.ego_to_image).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from ..geometry import invert_transforms, is_rigid, make_transform
from .errors import BadInput


@dataclass
class CameraCalibration:
    """intrinsics float64 [3, 3] of the original image; image_hw (H, W); sensor2ego [4, 4]."""

    frame_id: str
    image_hw: tuple[int, int]
    intrinsics: np.ndarray
    sensor2ego: np.ndarray | None = None


@dataclass
class Rig:
    base_frame: str
    cameras: dict[str, CameraCalibration]


@dataclass(frozen=True)
class IntrinsicsRange:
    """Plausible pinhole intrinsics for an image of width W and height H: fx and fy within
    [min_focal, max_focal] * W (a 170 deg fisheye rectified to 0.1 W, a 5 deg tele lens at
    11 W) and the principal point within ``principal_margin`` * size of the image."""

    min_focal: float = 0.1
    max_focal: float = 20.0
    principal_margin: float = 0.5


def check_intrinsics(K, height: int, width: int, frame_id: str = "",
                     plausible: IntrinsicsRange | None = IntrinsicsRange()) -> CameraCalibration:
    """Validate a CameraInfo's K and size; raises ``BadInput('bad_camera_info')`` for an
    unusable one, ``BadInput('implausible_camera_info')`` for one out of ``plausible``."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    where = f" (frame {frame_id!r})" if frame_id else ""
    if height <= 0 or width <= 0:
        raise BadInput("bad_camera_info", f"CameraInfo{where} has size {height}x{width}")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 \
            or np.any(K[2, :2] != 0):
        raise BadInput("bad_camera_info", f"CameraInfo{where} has an unusable K "
                       f"(uncalibrated camera?): {K.ravel().tolist()}")
    if plausible is not None:
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        lo, hi, margin = plausible.min_focal * width, plausible.max_focal * width, \
            plausible.principal_margin
        if not (lo <= fx <= hi and lo <= fy <= hi):
            raise BadInput("implausible_camera_info", f"CameraInfo{where}: focal length "
                           f"fx={fx:.4g}, fy={fy:.4g} px outside [{lo:.4g}, {hi:.4g}] for an "
                           f"image {width} px wide")
        if not (-margin * width <= cx <= (1 + margin) * width
                and -margin * height <= cy <= (1 + margin) * height):
            raise BadInput("implausible_camera_info", f"CameraInfo{where}: principal point "
                           f"({cx:.4g}, {cy:.4g}) px far outside the {width}x{height} image")
    return CameraCalibration(frame_id=frame_id, image_hw=(int(height), int(width)), intrinsics=K)


def load_rig(path: str | Path) -> Rig:
    """Read a rig YAML file (format in config/rig_nuscenes.yaml). Raises ValueError if bad."""
    with open(path) as f:
        doc = yaml.safe_load(f) or {}
    if "cameras" not in doc or not isinstance(doc["cameras"], dict) or not doc["cameras"]:
        raise ValueError(f"{path}: no 'cameras' mapping")
    cameras = {}
    for name, entry in doc["cameras"].items():
        try:
            height, width = (int(v) for v in entry["image_size"])
            calibration = check_intrinsics(entry["intrinsics"], height, width,
                                           entry.get("frame_id", name))
            extrinsics = entry["sensor2ego"]
            T = make_transform(extrinsics["rotation"], extrinsics["translation"])
        except KeyError as error:
            raise ValueError(f"{path}: camera {name}: no {error.args[0]!r} (a rig file gives "
                             "each camera image_size, intrinsics and sensor2ego)") from None
        except (TypeError, ValueError, BadInput) as error:
            raise ValueError(f"{path}: camera {name}: {error}") from None
        if not is_rigid(T):
            raise ValueError(f"{path}: camera {name}: sensor2ego is not rigid")
        calibration.sensor2ego = T
        cameras[name] = calibration
    return Rig(base_frame=str(doc.get("base_frame", "base_link")), cameras=cameras)


def set_ego2img(input_intrinsics, sensor2ego, camera_poses, reference_pose) -> np.ndarray:
    """ego->image matrices of one set, each camera at its own stamp.

    input_intrinsics [N, 3, 3] (network input), sensor2ego [N, 4, 4] (T_ego_from_cam),
    camera_poses [N, 4, 4] T_global_from_ego at each camera's stamp,
    reference_pose [4, 4] T_global_from_ego at the reference stamp -> float64 [N, 4, 4].
    One stacked computation for the N cameras (NumPy on 4x4 matrices costs its per-call
    overhead, not arithmetic); the same products as geometry.ego_to_image per camera.
    Raises ValueError if an extrinsic or a pose is not rigid.
    """
    input_intrinsics = np.asarray(input_intrinsics, dtype=np.float64)
    reference_pose = np.asarray(reference_pose, dtype=np.float64)
    projection = np.zeros((len(input_intrinsics), 4, 4))
    projection[:, :3, :3] = input_intrinsics
    projection[:, 3, 3] = 1.0
    ego_t_from_ego_ref = invert_transforms(camera_poses) @ reference_pose
    return (projection @ invert_transforms(sensor2ego)) @ ego_t_from_ego_ref
