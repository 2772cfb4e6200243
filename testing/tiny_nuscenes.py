"""A tiny hand-made nuScenes-format dataroot (JSON tables + JPEGs + LiDAR .pcd.bin) with known
ego motion, for the bag and replay tests. Images are 64 x 36 and of one colour per
(camera, frame), so a decoded JPEG can be told apart from any other.

Ego motion: constant speed along the heading and constant yaw rate, so /odom's twist has a
closed form: linear = (SPEED, 0, 0) in base_link, angular = (0, 0, YAW_RATE).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from odg_ros import geometry
from odg_ros.nuscenes_cameras import CAMERA_NAMES

VERSION = "v1.0-tiny"
WIDTH, HEIGHT = 64, 36
SPEED = 5.0      # m/s along base_link x
YAW_RATE = 0.2   # rad/s about z
CAMERA_YAWS_DEG = {"CAM_FRONT": 0, "CAM_FRONT_RIGHT": -55, "CAM_FRONT_LEFT": 55,
                   "CAM_BACK": 180, "CAM_BACK_LEFT": 110, "CAM_BACK_RIGHT": -110}
# Optical camera frame (x right, y down, z forward) -> ego (x forward, y left, z up).
R_EGO_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def ego_pose_at(t_s: float, start_xy=(100.0, 200.0), start_yaw=0.3) -> np.ndarray:
    """T_global_from_ego on a circular arc (constant SPEED and YAW_RATE)."""
    yaw = start_yaw + YAW_RATE * t_s
    radius = SPEED / YAW_RATE
    x = start_xy[0] + radius * (np.sin(yaw) - np.sin(start_yaw))
    y = start_xy[1] - radius * (np.cos(yaw) - np.cos(start_yaw))
    c, s = np.cos(yaw), np.sin(yaw)
    return geometry.make_transform(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), [x, y, 0.5])


def colour(scene_index: int, cam_index: int, frame: int) -> tuple[int, int, int]:
    return (40 * cam_index + 20, (37 * frame) % 200 + 30, 100 + 80 * scene_index)


def _token(*parts) -> str:
    return "-".join(str(p) for p in parts)


def build(root: Path, scene_durations_s=(1.0, 0.5), with_lidar=True) -> dict:
    """Write the dataroot; returns what a bag of each scene must contain."""
    root = Path(root)
    tables = {name: [] for name in ("log", "scene", "sample", "sample_data", "ego_pose",
                                    "calibrated_sensor", "sensor")}
    K = np.array([[40.0, 0.0, WIDTH / 2], [0.0, 40.0, HEIGHT / 2], [0.0, 0.0, 1.0]])
    calib_tokens = {}
    for channel in list(CAMERA_NAMES) + ["LIDAR_TOP"]:
        tables["sensor"].append({"token": _token("sensor", channel), "channel": channel,
                                 "modality": "lidar" if channel == "LIDAR_TOP" else "camera"})
        if channel == "LIDAR_TOP":
            R, t, intr = np.eye(3), [0.9, 0.0, 1.8], []
        else:
            yaw = np.deg2rad(CAMERA_YAWS_DEG[channel])
            Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0],
                           [0, 0, 1]])
            R, t, intr = Rz @ R_EGO_FROM_OPTICAL, [1.5 * np.cos(yaw), 0.5 * np.sin(yaw), 1.6], \
                K.tolist()
        calib_tokens[channel] = _token("calib", channel)
        tables["calibrated_sensor"].append({
            "token": calib_tokens[channel], "sensor_token": _token("sensor", channel),
            "translation": list(map(float, t)),
            "rotation": geometry.matrix_to_quaternion(R).tolist(), "camera_intrinsic": intr})

    expected = {}
    t0_us = 1_533_151_603_547_590
    for scene_index, duration in enumerate(scene_durations_s):
        name = f"scene-{scene_index + 1:04d}"
        scene_token = _token("scene", scene_index)
        start_us = t0_us + scene_index * 60_000_000
        keyframes = [start_us + int(k * 500_000) for k in range(int(duration / 0.5) + 1)]
        sample_tokens = [_token("sample", scene_index, k) for k in range(len(keyframes))]
        for k, (tok, ts) in enumerate(zip(sample_tokens, keyframes)):
            tables["sample"].append({
                "token": tok, "timestamp": ts, "scene_token": scene_token,
                "prev": sample_tokens[k - 1] if k else "",
                "next": sample_tokens[k + 1] if k + 1 < len(sample_tokens) else ""})
        tables["log"].append({"token": _token("log", scene_index), "location": "tiny"})
        tables["scene"].append({"token": scene_token, "name": name,
                                "log_token": _token("log", scene_index),
                                "nbr_samples": len(keyframes),
                                "first_sample_token": sample_tokens[0],
                                "last_sample_token": sample_tokens[-1], "description": "tiny"})

        def nearest_sample(ts):
            return sample_tokens[int(np.argmin([abs(ts - k) for k in keyframes]))]

        counts = {}
        stamps = set()
        records = []  # (channel, ts, is_key, filename)
        end_us = keyframes[-1]
        # LiDAR at 20 Hz starting at each keyframe; cameras at 12 Hz, 7..40 ms after.
        lidar_stamps = list(range(start_us, end_us + 1, 50_000)) if with_lidar else []
        for i, ts in enumerate(lidar_stamps):
            is_key = ts in keyframes
            folder = "samples" if is_key else "sweeps"
            records.append(("LIDAR_TOP", ts, is_key,
                            f"{folder}/LIDAR_TOP/{name}__LIDAR_TOP__{ts}.pcd.bin", i))
        cam_sets = list(range(start_us, end_us + 1, 83_333))
        for frame, set_start in enumerate(cam_sets):
            for cam_index, cam in enumerate(CAMERA_NAMES):
                ts = set_start + 7_000 + 6_500 * cam_index
                is_key = set_start in keyframes
                folder = "samples" if is_key else "sweeps"
                records.append((cam, ts, is_key, f"{folder}/{cam}/{name}__{cam}__{ts}.jpg",
                                frame))
        for channel, ts, is_key, filename, frame in records:
            path = root / filename
            path.parent.mkdir(parents=True, exist_ok=True)
            if channel == "LIDAR_TOP":
                rng = np.random.default_rng(ts % 2**32)
                pts = rng.normal(size=(50, 5)).astype(np.float32)
                pts[:, 4] = np.arange(50) % 32
                pts.tofile(path)
            else:
                cam_index = CAMERA_NAMES.index(channel)
                Image.new("RGB", (WIDTH, HEIGHT), colour(scene_index, cam_index, frame)).save(
                    path, quality=95)
            pose_token = _token("pose", channel, ts)
            T = ego_pose_at((ts - start_us) * 1e-6)
            tables["ego_pose"].append({
                "token": pose_token, "timestamp": ts, "translation": T[:3, 3].tolist(),
                "rotation": geometry.matrix_to_quaternion(T[:3, :3]).tolist()})
            tables["sample_data"].append({
                "token": _token("sd", channel, ts), "sample_token": nearest_sample(ts),
                "ego_pose_token": pose_token, "calibrated_sensor_token": calib_tokens[channel],
                "timestamp": ts, "fileformat": "pcd" if channel == "LIDAR_TOP" else "jpg",
                "is_key_frame": is_key, "height": 0 if channel == "LIDAR_TOP" else HEIGHT,
                "width": 0 if channel == "LIDAR_TOP" else WIDTH, "filename": filename,
                "prev": "", "next": ""})
            topic_counts = ([f"/{channel}"] if channel == "LIDAR_TOP"
                            else [f"/{channel}/image_rect_compressed", f"/{channel}/camera_info"])
            for topic in topic_counts:
                counts[topic] = counts.get(topic, 0) + 1
            stamps.add(ts)
        counts["/tf"] = counts["/odom"] = len(stamps)
        counts["/tf_static"] = 1
        expected[name] = {"counts": counts, "start_us": start_us, "scene_index": scene_index}

    folder = root / VERSION
    folder.mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        (folder / f"{name}.json").write_text(json.dumps(rows))
    return expected
