"""``odg prepare``: the infos index (contract: odg_ros/data/batch.py) of a nuScenes-format
dataroot with Occ3D-nuScenes ground truth (``<occ root>/<scene name>/<sample token>/labels.npz``).

Per keyframe: the six cameras of its set, the earlier 12 Hz camera sets back to the previous
keyframe (newest first; the dataset continues with the previous keyframes itself), the LiDAR
path + calibration + lidarseg path, the Occ3D path, and the 3D boxes in the keyframe's ego
frame with nuScenes-devkit velocities. Annotations without any LiDAR or radar point are
dropped (mmdet3d's ``valid_flag``); categories without a detection class are skipped.

Splits: ``<dataroot>/splits.json`` when present (``odg synth`` writes one), else the
nuscenes-devkit's official split lists (train/val for v1.0-trainval, mini_train/mini_val for
v1.0-mini, test for v1.0-test).
"""
from __future__ import annotations

import json
import os
import pickle

import numpy as np
from tqdm import tqdm

from ..classes import BOX_CLASSES
from ..geometry import invert_transform, quaternion_to_matrix
from ..nuscenes_cameras import CAMERA_NAMES
from ..rotation import yaw_of
from .nuscenes_tables import CATEGORY_TO_BOX_CLASS, NuScenesTables, pose_matrix

MAX_SWEEP_SETS = 12        # safety cap; nuScenes has 5 camera sets between keyframes
SET_TOLERANCE_US = 60_000  # cameras of one set lie within ~42 ms of CAM_FRONT (docs/architecture.md sec. 2)


def split_scene_names(dataroot, version, split, tables: NuScenesTables) -> list[str]:
    """Scene names of ``split`` ('train', 'val', 'all', or a devkit split name)."""
    names = [s["name"] for s in tables.scenes()]
    if split == "all":
        return names
    path = os.path.join(str(dataroot), "splits.json")
    if os.path.exists(path):
        with open(path) as f:
            splits = json.load(f)
        if split not in splits:
            raise ValueError(f"split {split!r} not in {path} (has {sorted(splits)})")
        wanted = set(splits[split])
    else:
        try:
            from nuscenes.utils.splits import create_splits_scenes
        except ImportError as e:
            raise RuntimeError(f"no {path}; the official nuScenes splits need nuscenes-devkit "
                               f"(pip install nuscenes-devkit) or use --split all") from e
        official = create_splits_scenes(verbose=False)
        key = {"v1.0-mini": {"train": "mini_train", "val": "mini_val"}}.get(version, {}).get(split, split)
        if key not in official:
            raise ValueError(f"unknown split {split!r} for {version}")
        wanted = set(official[key])
    return [n for n in names if n in wanted]


def _camera(tables: NuScenesTables, sd) -> dict:
    calib = tables.calibration(sd)
    if not calib.get("camera_intrinsic"):
        raise ValueError(f"sample_data {sd['token']} has no camera intrinsics")
    return {"data_path": sd["filename"], "timestamp": int(sd["timestamp"]),
            "intrinsics": np.asarray(calib["camera_intrinsic"], np.float64),
            "sensor2ego": pose_matrix(calib), "ego_pose": tables.ego_pose(sd),
            "image_hw": (int(sd["height"]), int(sd["width"])), "token": sd["token"]}


def _earlier_sets(tables: NuScenesTables, key_sds: dict) -> list[dict]:
    """Camera sets before a keyframe back to (not including) the previous keyframe, newest
    first; cameras are matched to CAM_FRONT's sweep by nearest stamp."""
    chains = {}
    for name in CAMERA_NAMES:
        chain, tok = [], key_sds[name]["prev"]
        while tok and len(chain) < MAX_SWEEP_SETS + 2:
            sd = tables.get("sample_data", tok)
            if sd["is_key_frame"]:
                break
            chain.append(sd)
            tok = sd["prev"]
        chains[name] = chain
    sets = []
    for ref in chains[CAMERA_NAMES[0]][:MAX_SWEEP_SETS]:
        cam_set = {}
        for name in CAMERA_NAMES:
            if not chains[name]:
                continue
            best = min(chains[name], key=lambda sd: abs(sd["timestamp"] - ref["timestamp"]))
            if abs(best["timestamp"] - ref["timestamp"]) <= SET_TOLERANCE_US:
                cam_set[name] = _camera(tables, best)
        sets.append(cam_set)
    return sets


def _boxes(tables: NuScenesTables, sample, T_global_from_ego):
    """(gt_boxes [M, 9] float64, gt_labels [M] int64) in the ego frame."""
    T_ego_global = invert_transform(T_global_from_ego)
    R_ego_global = T_ego_global[:3, :3]
    boxes, labels = [], []
    for ann in tables.annotations.get(sample["token"], []):
        cls = CATEGORY_TO_BOX_CLASS.get(tables.category_name(ann))
        if cls is None:
            continue
        if ann.get("num_lidar_pts", 1) + ann.get("num_radar_pts", 0) <= 0:
            continue
        centre = T_ego_global[:3, :3] @ np.asarray(ann["translation"], float) + T_ego_global[:3, 3]
        R = R_ego_global @ quaternion_to_matrix(ann["rotation"])
        yaw = yaw_of(R)
        v = R_ego_global @ np.nan_to_num(tables.annotation_velocity(ann), nan=0.0)
        w, l, h = ann["size"]
        boxes.append([*centre, w, l, h, yaw, v[0], v[1]])
        labels.append(BOX_CLASSES.index(cls))
    return np.asarray(boxes, np.float64).reshape(-1, 9), np.asarray(labels, np.int64)


def build_infos(dataroot, occ_root=None, version="v1.0-trainval", split="train", progress=True) -> dict:
    """The infos dict of one split (see odg_ros/data/batch.py)."""
    dataroot = os.path.abspath(str(dataroot))
    occ_root = os.path.abspath(str(occ_root)) if occ_root else os.path.join(dataroot, "gts")
    tables = NuScenesTables(dataroot, version)
    names = set(split_scene_names(dataroot, version, split, tables))
    scenes = [s for s in tables.scenes() if s["name"] in names]
    infos = []
    total = sum(s["nbr_samples"] for s in scenes)
    bar = tqdm(total=total, unit="keyframe", desc=f"odg prepare {split}", disable=not progress)
    for scene in scenes:
        for frame_index, sample in enumerate(tables.scene_samples(scene)):
            sds = tables.keyframe_data.get(sample["token"], {})
            missing = [c for c in CAMERA_NAMES + ("LIDAR_TOP",) if c not in sds]
            if missing:
                raise ValueError(f"sample {sample['token']} ({scene['name']}) lacks keyframe data for {missing}")
            lidar = sds["LIDAR_TOP"]
            T_global_from_ego = tables.ego_pose(lidar)
            occ_rel = os.path.join(scene["name"], sample["token"], "labels.npz")
            gt_boxes, gt_labels = _boxes(tables, sample, T_global_from_ego)
            infos.append({
                "token": sample["token"], "scene_token": scene["token"], "scene_name": scene["name"],
                "timestamp": int(sample["timestamp"]), "frame_index": frame_index,
                "ego_pose": T_global_from_ego,
                "lidar_path": lidar["filename"], "lidar2ego": pose_matrix(tables.calibration(lidar)),
                "lidarseg_path": tables.lidarseg.get(lidar["token"], ""),
                "cams": {name: _camera(tables, sds[name]) for name in CAMERA_NAMES},
                "sweeps": _earlier_sets(tables, sds),
                "occ_path": occ_rel if os.path.exists(os.path.join(occ_root, occ_rel)) else "",
                "gt_boxes": gt_boxes, "gt_labels": gt_labels,
            })
            bar.update(1)
    bar.close()
    rel = os.path.relpath(occ_root, dataroot)
    return {"version": version, "dataset": "nuscenes", "dataroot": dataroot,
            "occ_root": occ_root if rel.startswith("..") else rel, "split": split, "infos": infos}


def save_infos(infos: dict, path) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(str(path))), exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump(infos, f, protocol=4)


def load_infos(path) -> dict:
    """Read an infos pickle and check its top level (raises ValueError on a foreign file)."""
    with open(path, "rb") as f:
        infos = pickle.load(f)
    if not isinstance(infos, dict) or not {"version", "dataset", "dataroot", "infos"} <= set(infos):
        raise ValueError(f"{path} is not an odg infos file (need version, dataset, dataroot, infos)")
    if not isinstance(infos["infos"], list):
        raise ValueError(f"{path}: 'infos' must be a list of keyframes")
    return infos
