"""A tiny nuScenes-format world on disk for the data tests: six cameras on a car driving
straight, images, LiDAR sweeps, poses and Occ3D ground truth."""
from __future__ import annotations

import numpy as np
from PIL import Image

from odg_ros import geometry
from odg_ros.classes import FREE_LABEL
from odg_ros.data import lidar
from odg_ros.nuscenes_cameras import CAMERA_NAMES

IMAGE_HW = (90, 160)
FOCAL, CX, CY = 100.0, 80.0, 45.0
CAM_T = (1.5, 0.0, 1.6)        # every camera sits here on the ego
CAM_YAWS = (0.0, -55.0, 55.0, 180.0, 110.0, -110.0)  # degrees, CAMERA_NAMES order
SET_PERIOD_US = 1_000_000 // 12
CAM_OFFSET_US = (7_000, 8_000)  # first camera after the set time, then per camera
T0_US = 1_533_151_603_547_590
SPEED = 10.0                    # m/s along global x
ORIGIN = np.array([600.0, 1600.0, 0.0])
LIDAR2EGO = geometry.make_transform(np.eye(3), (0.9, 0.0, 1.8))


def R_ego_from_front_cam():
    # camera x right, y down, z forward -> ego x forward, y left, z up
    return np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def Rz(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def ego_pose(stamp_us, yaw_rate=0.0):
    tau = (stamp_us - T0_US) * 1e-6
    return geometry.make_transform(Rz(np.rad2deg(yaw_rate * tau)), ORIGIN + [SPEED * tau, 0, 0])


def colour(set_index, cam):
    return (20 * (set_index % 12) + 10, 40 * cam + 5, 200 - 10 * (set_index // 12))


def build_world(root, num_keyframes=3, yaw_rate=0.0, sweeps_span_all=False, with_lidar=True,
                occ=True):
    """Write JPEGs (+ LiDAR, lidarseg, labels.npz) under root; return the infos dict."""
    intr = np.array([[FOCAL, 0, CX], [0, FOCAL, CY], [0, 0, 1.0]])
    sets = []
    for j in range((num_keyframes - 1) * 6 + 1):
        set_us = T0_US + j * SET_PERIOD_US
        cams = {}
        for n, name in enumerate(CAMERA_NAMES):
            stamp = set_us + CAM_OFFSET_US[0] + n * CAM_OFFSET_US[1]
            rel = f"samples/{name}/set{j:03d}.jpg"
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            Image.new("RGB", IMAGE_HW[::-1], colour(j, n)).save(root / rel, quality=95)
            cams[name] = dict(
                data_path=rel, timestamp=stamp, intrinsics=intr.copy(),
                sensor2ego=geometry.make_transform(Rz(CAM_YAWS[n]) @ R_ego_from_front_cam(), CAM_T),
                ego_pose=ego_pose(stamp, yaw_rate), image_hw=IMAGE_HW)
        sets.append((set_us, cams))
    infos = []
    for k in range(num_keyframes):
        j = 6 * k
        set_us, cams = sets[j]
        # mmdet3d style: the sets between the previous keyframe and this one, newest first;
        # or (sweeps_span_all) every earlier set of the scene
        oldest = 0 if sweeps_span_all else max(0, j - 5)
        sweeps = [sets[i][1] for i in range(j - 1, oldest - 1, -1)]
        info = dict(token=f"kf{k}", scene_token="scene0", scene_name="scene-0001",
                    timestamp=set_us, frame_index=k, ego_pose=ego_pose(set_us, yaw_rate),
                    lidar_path="", lidar2ego=LIDAR2EGO, cams=cams, sweeps=sweeps, occ_path="",
                    gt_boxes=np.array([[10.0, 2.0, 0.8, 1.9, 4.5, 1.6, 0.3, 5.0, 0.0]]),
                    gt_labels=np.array([0]))
        if occ:
            info["occ_path"] = f"scene-0001/kf{k}/labels.npz"
            sem = np.full((200, 200, 16), FREE_LABEL, np.uint8)
            sem[130, 102, 6] = 4
            mask = np.zeros((200, 200, 16), np.uint8)
            mask[120:140, 90:110, :] = 1
            (root / "gts" / info["occ_path"]).parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(root / "gts" / info["occ_path"], semantics=sem, mask_lidar=mask,
                                mask_camera=mask)
        infos.append(info)
    if with_lidar:
        write_lidar(root, infos[-1])
    return {"version": "test", "dataset": "nuscenes", "dataroot": str(root), "infos": infos}


# Points of the last keyframe's sweep, in its ego frame, with raw nuScenes-lidarseg labels:
# 17 = vehicle.car, 24 = flat.driveable_surface, 30 = static.vegetation, 9 = movable_object.barrier
NEAR = np.array([11.5, 1.0, 1.6])


def lidar_points_ego():
    # in camera-stamp ego coords the front camera sees NEAR at depth 10 - motion; FAR lies on the
    # same viewing ray at twice the distance (hidden), BACK is behind the ego, CLOSE is 0.5 m
    # in front of the front camera (dropped: < 1 m), OUT is far outside every image
    front_shift = SPEED * CAM_OFFSET_US[0] * 1e-6
    cam_centre = np.array(CAM_T) + [front_shift, 0, 0]      # in keyframe ego coordinates
    far = cam_centre + 2 * (NEAR - cam_centre)
    back = np.array([-10.0, 0.0, 1.6])
    close = cam_centre + [0.5, 0.0, 0.0]
    out = np.array([0.0, 0.0, 60.0])
    return np.stack([NEAR, far, back, close, out]), np.array([17, 30, 24, 9, 17], np.uint8)


def write_lidar(root, info):
    points_ego, raw = lidar_points_ego()
    points_lidar = lidar.transform_points(geometry.invert_transform(LIDAR2EGO), points_ego)
    rec = np.zeros((len(points_lidar), 5), np.float32)
    rec[:, :3] = points_lidar
    rec[:, 3] = 7.0
    info["lidar_path"] = "samples/LIDAR_TOP/kf.pcd.bin"
    info["lidarseg_path"] = "lidarseg/v1.0-mini/kf_lidarseg.bin"
    for rel in (info["lidar_path"], info["lidarseg_path"]):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
    rec.tofile(root / info["lidar_path"])
    raw.tofile(root / info["lidarseg_path"])
