"""``odg synth --layout waymo``: the synthetic world written in the Occ3D-Waymo layout that
``odg prepare --layout waymo`` reads (odg_ros/data/prepare_waymo.py).

The world is generated in the nuScenes layout first (generate.py), indexed with odg prepare,
then rewritten: one Waymo frame per keyframe (2 per second: prepare with ``--frame-hz 2``),
each camera's pose given relative to the keyframe's ego pose (the GT's frame),
five of the six cameras (the rear one dropped, as Waymo has none), the pose files in their
camera order, and the GT with the Waymo label set (nuScenes classes mapped to the closest
Waymo class, free stored as 23 as in the release, ``infov`` = the voxel centres inside the five
cameras' images). Training scenes go under ``training/``, validation scenes under
``validation/`` (images of both under ``training/image_<k>/``, prefix 0 / 1).
"""
from __future__ import annotations

import json
import os
import pickle
import shutil
import tempfile

import numpy as np

from ...classes import OCC_CLASSES, WAYMO_OCC_CLASSES
from ...geometry import invert_transform
from .. import occ_io
from ..prepare import build_infos
from ..prepare_waymo import WAYMO_CAMERA_NAMES, SPLITS

# Waymo camera (image folder order) <- synthetic nuScenes camera.
SOURCE_CAMERA = {"FRONT": "CAM_FRONT", "FRONT_LEFT": "CAM_FRONT_LEFT",
                 "FRONT_RIGHT": "CAM_FRONT_RIGHT", "SIDE_LEFT": "CAM_BACK_LEFT",
                 "SIDE_RIGHT": "CAM_BACK_RIGHT"}
_NUSCENES_TO_WAYMO_NAME = {
    "others": "general_object", "barrier": "general_object", "bicycle": "bicycle",
    "bus": "vehicle", "car": "vehicle", "construction_vehicle": "vehicle",
    "motorcycle": "motorcycle", "pedestrian": "pedestrian", "traffic_cone": "construction_cone",
    "trailer": "vehicle", "truck": "vehicle", "driveable_surface": "road", "other_flat": "road",
    "sidewalk": "walkable", "terrain": "walkable", "manmade": "building",
    "vegetation": "vegetation",
}
# The release's pose files list the cameras in this order (the image folders in WAYMO_CAMERA_NAMES'
# order); written out here on its own so that prepare's pairing is checked, not copied.
POSE_FILE_ORDER = ("FRONT", "FRONT_LEFT", "SIDE_LEFT", "FRONT_RIGHT", "SIDE_RIGHT")
# nuScenes label (0..17) -> label in a released Occ3D-Waymo file (0..14, free 23)
NUSCENES_TO_WAYMO_FILE = np.array(
    [WAYMO_OCC_CLASSES.index(_NUSCENES_TO_WAYMO_NAME[n]) for n in OCC_CLASSES[:-1]]
    + [occ_io.WAYMO_FILE_FREE_LABEL], np.uint8)


def in_camera_view(cams: dict, grid_shape=occ_io.GRID_SHAPE, pc_range=(-40, -40, -1, 40, 40, 5.4),
                   voxel_size=0.4) -> np.ndarray:
    """bool [X, Y, Z]: the voxel centre lies in front of and inside at least one image."""
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in grid_shape], indexing="ij"), -1)
    centres = (idx.reshape(-1, 3) + 0.5) * voxel_size + np.asarray(pc_range[:3])
    homo = np.concatenate([centres, np.ones((len(centres), 1))], 1)
    seen = np.zeros(len(centres), bool)
    for cam in cams.values():
        in_cam = homo @ invert_transform(cam["sensor2ego"]).T
        z = in_cam[:, 2]
        uv = in_cam[:, :3] @ np.asarray(cam["intrinsics"]).T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uv[:, 0] / z, uv[:, 1] / z
        h, w = cam["image_hw"]
        seen |= (z > 0.1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return seen.reshape(grid_shape)


def _place_image(src: str, dst: str) -> None:
    os.makedirs(os.path.dirname(dst), exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def write_waymo_layout(source_infos: dict, out: str) -> dict:
    """Rewrite a synthetic world's infos (``dataset: nuscenes``) under ``out`` in the
    Occ3D-Waymo layout. Returns {split: number of scenes}."""
    src_root = source_infos["dataroot"]
    occ_src = os.path.join(src_root, source_infos["occ_root"])
    by_scene: dict[str, list] = {}
    for info in source_infos["infos"]:
        by_scene.setdefault(info["scene_name"], []).append(info)
    with open(os.path.join(src_root, "splits.json")) as f:
        splits = json.load(f)
    counts = {}
    for split, (pose_file, gt_folder, prefix) in SPLITS.items():
        names = [n for n in sorted(by_scene) if n in splits.get(split, ())]
        poses = {}
        for scene, name in enumerate(names):
            frames = {}
            for frame, info in enumerate(sorted(by_scene[name], key=lambda i: i["timestamp"])):
                # Each camera relative to the keyframe's ego pose (the GT's frame): the same
                # camera -> global transform, and one ego pose per frame as the GT needs.
                key_pose = np.asarray(info["ego_pose"], np.float64)
                cams = {}
                for w in WAYMO_CAMERA_NAMES:
                    c = info["cams"][SOURCE_CAMERA[w]]
                    cams[w] = {**c, "ego_pose": key_pose, "sensor2ego": invert_transform(key_pose)
                               @ np.asarray(c["ego_pose"]) @ np.asarray(c["sensor2ego"])}
                stem = f"{prefix}{scene:03d}{frame:03d}"
                for folder, w in enumerate(WAYMO_CAMERA_NAMES):
                    _place_image(os.path.join(src_root, cams[w]["data_path"]),
                                 os.path.join(out, "training", f"image_{folder}", stem + ".jpg"))
                frames[frame] = {k: {"ego2global": cams[w]["ego_pose"],
                                     "sensor2ego": cams[w]["sensor2ego"],
                                     "intrinsics": cams[w]["intrinsics"]}
                                 for k, w in enumerate(POSE_FILE_ORDER)}
                if not info["occ_path"]:
                    continue
                semantics, mask_lidar, mask_camera = occ_io.load_occ3d_nuscenes(
                    os.path.join(occ_src, info["occ_path"]))
                gt = os.path.join(out, gt_folder, f"{scene:03d}", f"{frame:03d}_04.npz")
                os.makedirs(os.path.dirname(gt), exist_ok=True)
                np.savez_compressed(gt, voxel_label=NUSCENES_TO_WAYMO_FILE[semantics],
                                    origin_voxel_state=mask_lidar.astype(np.uint8),
                                    final_voxel_state=mask_camera.astype(np.uint8),
                                    infov=in_camera_view(cams, semantics.shape).astype(np.uint8))
            poses[scene] = frames
        with open(os.path.join(out, pose_file), "wb") as f:
            pickle.dump(poses, f, protocol=4)
        counts[split] = len(names)
    return counts


def generate_waymo(out: str, **generate_options) -> dict:
    """``generate`` into a scratch folder, rewrite it under ``out`` in the Occ3D-Waymo layout,
    remove the scratch folder. Returns generate's summary with ``split`` = {split: scenes}."""
    from .generate import generate
    if os.path.exists(os.path.join(out, SPLITS["train"][0])):
        raise FileExistsError(f"{out} already holds an Occ3D-Waymo world; choose an empty --out")
    os.makedirs(out, exist_ok=True)
    scratch = tempfile.mkdtemp(prefix=".nuscenes_layout_", dir=out)
    try:
        summary = generate(scratch, progress=generate_options.pop("progress", True),
                           **generate_options)
        infos = build_infos(scratch, version=generate_options.get("version", "v1.0-trainval"),
                            split="all", progress=False)
        summary["split"] = write_waymo_layout(infos, out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return summary
