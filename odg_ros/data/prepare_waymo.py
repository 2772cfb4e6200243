"""``odg prepare --layout waymo``: the infos index (contract: odg_ros/data/batch.py) of
Occ3D-Waymo.

Layout read (the images as mmdetection3d's Waymo converter writes them, the Occ3D-Waymo
release next to them or elsewhere)::

    <dataroot>/training/image_<k>/<P><SSS><FFF>.jpg   camera image folder k = 0..4; P = 0 for
                                                      training, 1 for validation scenes (both
                                                      under training/); SSS scene, FFF frame
    <occ root>/cam_infos.pkl       training poses:   {scene: {frame: {camera: {"ego2global",
    <occ root>/cam_infos_vali.pkl  validation poses:   "sensor2ego", "intrinsics"}}}}
    <occ root>/training/<SSS>/<FFF>_04.npz            occupancy GT (keys: data/occ_io.py)
    <occ root>/validation/<SSS>/<FFF>_04.npz

Cameras. Image folders 0..4 are FRONT, FRONT_LEFT, FRONT_RIGHT, SIDE_LEFT, SIDE_RIGHT (the
Occ3D-Waymo README). The pose files list the cameras in another order: pose entry k belongs
to image folder ``IMAGE_FOLDER_OF_POSE[k]`` (entries 2 and 3 are swapped, as public
Occ3D-Waymo loaders correct). A principal point outside its image is refused, so a pairing
that disagrees with the data shows at once. ``sensor2ego`` is the camera -> ego transform of
an OpenCV camera (x right, y down, z forward); one given in Waymo's camera axes (x forward,
y left, z up, optical axis horizontal along x) is converted, with a note.

Time. Waymo records 10 frames per second and the pose files hold no stamps: frame f is at
``f / frame_hz`` s. Every ``keyframe_interval``-th frame is a keyframe; the frames between
two keyframes are the later keyframe's ``sweeps`` (newest first), so the dataset's history
frames see every frame.

Not read: Waymo's 3D boxes (the box head's classes are nuScenes'), LiDAR points (no render
targets). The LiDAR origin used by RayIoU is the top LiDAR's nominal mount in the ego frame.
"""
from __future__ import annotations

import os
import pickle

import numpy as np
from PIL import Image

from .. import geometry

WAYMO_CAMERA_NAMES = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT")
IMAGE_FOLDER_OF_POSE = (0, 1, 3, 2, 4)
SPLITS = {  # split -> (pose file, GT folder, image-name prefix)
    "train": ("cam_infos.pkl", "training", 0),
    "val": ("cam_infos_vali.pkl", "validation", 1),
}
FRAME_HZ = 10.0
IMAGE_EXTENSIONS = (".jpg", ".png")
# Waymo's top LiDAR sits ~1.43 m ahead of the rear axle, ~2.18 m above the ground (ego origin).
LIDAR_TOP_IN_EGO = np.array([[1, 0, 0, 1.43], [0, 1, 0, 0.0], [0, 0, 1, 2.18], [0, 0, 0, 1]],
                            np.float64)
# OpenCV camera axes expressed in Waymo's camera axes: x_w = z_cv, y_w = -x_cv, z_w = -y_cv.
WAYMO_FROM_OPENCV_CAMERA = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]],
                                    np.float64)


def _items(container) -> list:
    """(key, value) pairs of a dict (sorted by key) or a list (by index)."""
    if isinstance(container, dict):
        return sorted(container.items())
    return list(enumerate(container))


def _matrix(value, shape, what: str) -> np.ndarray:
    m = np.asarray(value, np.float64)
    if m.shape == (4, 4) and shape == (3, 3):
        m = m[:3, :3]
    if m.shape != shape or not np.isfinite(m).all():
        raise ValueError(f"{what}: expected a finite {shape} matrix, got {m.shape}")
    return m


def opencv_sensor2ego(sensor2ego: np.ndarray) -> tuple[np.ndarray, bool]:
    """(camera -> ego with OpenCV camera axes, converted?). A camera whose z axis is near
    vertical in the ego frame cannot be an OpenCV camera looking at the road: its axes are
    Waymo's (x forward) and are converted."""
    if abs(sensor2ego[2, 2]) > 0.7 and abs(sensor2ego[2, 0]) < 0.7:
        return sensor2ego @ WAYMO_FROM_OPENCV_CAMERA, True
    return sensor2ego, False


def image_path(dataroot, folder: int, prefix: int, scene: int, frame: int) -> str:
    """Relative path of an image (the first extension that exists; .jpg if none does)."""
    stem = os.path.join("training", f"image_{folder}", f"{prefix}{scene:03d}{frame:03d}")
    for ext in IMAGE_EXTENSIONS:
        if os.path.exists(os.path.join(str(dataroot), stem + ext)):
            return stem + ext
    return stem + IMAGE_EXTENSIONS[0]


def _camera_set(dataroot, pose_frame, prefix, scene, frame, stamp, sizes, notes) -> dict:
    cams = dict(_items(pose_frame))
    if len(cams) != len(WAYMO_CAMERA_NAMES):
        raise ValueError(f"scene {scene} frame {frame}: {len(cams)} cameras in the pose file, "
                         f"expected {len(WAYMO_CAMERA_NAMES)}")
    out = {}
    for k, (_, cam) in enumerate(sorted(cams.items())):
        folder = IMAGE_FOLDER_OF_POSE[k]
        name = WAYMO_CAMERA_NAMES[folder]
        what = f"scene {scene} frame {frame} camera {k}"
        missing = [key for key in ("intrinsics", "sensor2ego", "ego2global") if key not in cam]
        if missing:
            raise ValueError(f"{what}: the pose file lacks {missing} (has {sorted(cam)})")
        rel = image_path(dataroot, folder, prefix, scene, frame)
        if name not in sizes:
            path = os.path.join(str(dataroot), rel)
            if not os.path.isfile(path):
                raise FileNotFoundError(f"image not found: {path} (expected mmdetection3d's "
                                        f"Waymo layout <dataroot>/training/image_<k>/)")
            with Image.open(path) as im:
                sizes[name] = (im.height, im.width)
        K = _matrix(cam["intrinsics"], (3, 3), f"{what} intrinsics")
        h, w = sizes[name]
        if not (0 < K[0, 2] < w and 0 < K[1, 2] < h):
            raise ValueError(f"{what}: principal point ({K[0, 2]:.0f}, {K[1, 2]:.0f}) lies outside "
                             f"its image {name} ({w} x {h}): the pose entries and image folders "
                             f"do not pair as IMAGE_FOLDER_OF_POSE says")
        sensor2ego, converted = opencv_sensor2ego(_matrix(cam["sensor2ego"], (4, 4),
                                                          f"{what} sensor2ego"))
        if converted:
            notes.add("sensor2ego in Waymo camera axes (x forward) converted to OpenCV axes")
        ego_pose = _matrix(cam["ego2global"], (4, 4), f"{what} ego2global")
        for m, label in ((sensor2ego, "sensor2ego"), (ego_pose, "ego2global")):
            if not geometry.is_rigid(m):
                raise ValueError(f"{what}: {label} is not a rigid transform")
        out[name] = {"data_path": rel, "timestamp": stamp, "intrinsics": K,
                     "sensor2ego": sensor2ego, "ego_pose": ego_pose, "image_hw": sizes[name],
                     "token": f"{prefix}{scene:03d}{frame:03d}_{name}"}
    return {name: out[name] for name in WAYMO_CAMERA_NAMES}


def build_waymo_infos(dataroot, occ_root=None, split="train", keyframe_interval: int = 1,
                      frame_hz: float = FRAME_HZ, scenes=None) -> tuple[dict, list[str]]:
    """(infos dict of one split, notes). ``scenes``: scene numbers to keep (default all)."""
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: Occ3D-Waymo has {' and '.join(SPLITS)}")
    if keyframe_interval < 1 or not frame_hz > 0:
        raise ValueError("keyframe_interval must be >= 1 and frame_hz > 0")
    dataroot = os.path.abspath(str(dataroot))
    occ_root = os.path.abspath(str(occ_root)) if occ_root else dataroot
    pose_file, gt_folder, prefix = SPLITS[split]
    pose_path = os.path.join(occ_root, pose_file)
    if not os.path.isfile(pose_path):
        raise FileNotFoundError(f"{pose_path} not found (the Occ3D-Waymo release's pose file; "
                                f"pass its folder as the occ root)")
    with open(pose_path, "rb") as f:
        poses = pickle.load(f)
    infos, notes = [], set()
    for scene, frames in _items(poses):
        scene = int(scene)
        if scenes is not None and scene not in scenes:
            continue
        sizes: dict = {}
        pending: list[dict] = []     # camera sets since the last keyframe, oldest first
        for frame_index, (frame, pose_frame) in enumerate(_items(frames)):
            frame = int(frame)
            stamp = int(round(frame * 1e6 / frame_hz))
            cams = _camera_set(dataroot, pose_frame, prefix, scene, frame, stamp, sizes, notes)
            if frame_index % keyframe_interval:
                pending.append(cams)
                continue
            occ_rel = os.path.join(gt_folder, f"{scene:03d}", f"{frame:03d}_04.npz")
            infos.append({
                "token": f"{prefix}{scene:03d}{frame:03d}", "scene_token": f"{split}-{scene:03d}",
                "scene_name": f"{gt_folder}/{scene:03d}", "timestamp": stamp,
                "frame_index": frame_index // keyframe_interval,
                "ego_pose": cams[WAYMO_CAMERA_NAMES[0]]["ego_pose"],
                "lidar_path": "", "lidar2ego": LIDAR_TOP_IN_EGO.copy(), "lidarseg_path": "",
                "cams": cams, "sweeps": pending[::-1],
                "occ_path": occ_rel if os.path.exists(os.path.join(occ_root, occ_rel)) else "",
                "gt_boxes": np.zeros((0, 9)), "gt_labels": np.zeros(0, np.int64),
            })
            pending = []
    rel = os.path.relpath(occ_root, dataroot)
    return ({"version": "occ3d-waymo", "dataset": "waymo", "dataroot": dataroot,
             "occ_root": occ_root if rel.startswith("..") else rel, "split": split,
             "infos": infos}, sorted(notes))
