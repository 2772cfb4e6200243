"""Write the synthetic dataset: a nuScenes-format dataroot with Occ3D ground truth.

Layout under ``out``::

    <version>/*.json                      nuScenes v1.0 tables (+ lidarseg.json)
    samples/CAM_*/*.jpg, sweeps/CAM_*/*.jpg
    samples/LIDAR_TOP/*.pcd.bin, sweeps/LIDAR_TOP/*.pcd.bin
    lidarseg/<version>/<lidar token>_lidarseg.bin
    gts/<scene name>/<sample token>/labels.npz   (semantics, mask_lidar, mask_camera)
    maps/<token>.png                      placeholder semantic-prior map (1 x 1 px)
    splits.json                           {"train": [scene names], "val": [...]}
    preview_cameras.png, preview_bev.png  the first scene's second keyframe, to look at

Every byte is a function of the seed (tokens are hashes, zips have fixed dates).
"""
from __future__ import annotations

import json
import os
import time

import numpy as np
from PIL import Image
from tqdm import tqdm

from ...geometry import invert_transform, matrix_to_quaternion
from ...nuscenes_cameras import CAMERA_NAMES
from ...rotation import yaw_to_quaternion
from . import occupancy, pictures, sensor_rig, sensors, shading
from .city import SceneKind, build_world
from .tables import Tables, link_chain, save_npz, token, visibility_token
from .world import World

DEFAULT_IMAGE_HW = (198, 352)
MASK_RAY_STEP = 0.006          # rad between the depth-map rays of mask_camera (~0.24 m at 40 m)
ANNOTATION_RANGE = 60.0        # annotate things whose centre is this close to the ego (xy, m)
BASE_TIMESTAMP_US = 1_533_000_000_000_000


def mask_ray_grid(cam: sensor_rig.Camera):
    """(intrinsics, (h, w)) of the depth map cast for mask_camera: the camera's field of view
    sampled every MASK_RAY_STEP radians, independent of the image size."""
    h, w = cam.image_hw
    cols = max(8, int(round(w / (cam.intrinsics[0, 0] * MASK_RAY_STEP))))
    rows = max(8, int(round(h / (cam.intrinsics[1, 1] * MASK_RAY_STEP))))
    K = cam.intrinsics.copy()
    K[0] *= cols / w
    K[1] *= rows / h
    return K, (rows, cols)


def num_keyframes(seconds: float) -> int:
    return max(1, int(round(seconds * sensor_rig.KEYFRAME_HZ)))


def scene_name(index: int) -> str:
    return f"scene-{index + 1:04d}"


def scene_world(seed: int, index: int, seconds: float, kind: SceneKind = SceneKind()) -> World:
    """The world of scene ``index`` exactly as ``generate`` builds it (tests rebuild it)."""
    duration = (num_keyframes(seconds) - 1) / sensor_rig.KEYFRAME_HZ + 0.2
    return build_world(np.random.SeedSequence([seed, index]), scene_name(index), duration,
                       kind)


def keyframe_time(k: int) -> float:
    """Seconds from the scene start to keyframe k's LiDAR stamp (end of its sweep)."""
    return (k * sensor_rig.SWEEPS_PER_KEYFRAME + 1) / sensor_rig.LIDAR_HZ


def camera_time(m: int, name: str) -> float:
    """Seconds from the scene start to camera ``name``'s exposure in camera set m."""
    return m / sensor_rig.CAMERA_HZ + sensor_rig.CAMERA_DELAY_S[name]


def camera_image(world: World, seed: int, index: int, m: int, ci: int, cam: sensor_rig.Camera, hw):
    """Camera ``cam`` (rig index ci) of camera set m of scene ``index``, exactly as ``generate``
    renders it: (exposure time, primitives then, ray hits, RGB uint8 image)."""
    t = camera_time(m, cam.name)
    prims = world.prims_at(t)
    T_global_cam = world.ego_pose(t) @ cam.T_ego_from_cam
    hits, dirs = sensors.render_camera(prims, T_global_cam, cam.intrinsics, hw)
    noise_seed = np.random.SeedSequence([seed, index, m, ci]).generate_state(1)[0]
    image = shading.shade(world, prims, hits, T_global_cam[:3, 3], dirs, hw, noise_seed,
                          camera_gain=1.0 + 0.04 * np.sin(ci * 2.1 + index))
    return t, prims, hits, image


def split_scenes(names: list[str]) -> dict:
    """Every fourth scene (at least one when there are two or more) goes to val."""
    val = [n for i, n in enumerate(names) if i % 4 == 3]
    if not val and len(names) >= 2:
        val = [names[-1]]
    return {"train": [n for n in names if n not in val], "val": val}


def _pose_record(tok, timestamp, T):
    return {"token": tok, "timestamp": int(timestamp),
            "rotation": [float(v) for v in matrix_to_quaternion(T[:3, :3])],
            "translation": [float(v) for v in T[:3, 3]]}


class _SceneWriter:
    def __init__(self, out, version, tables: Tables, seed, index, seconds, image_hw,
                 kind: SceneKind):
        self.out, self.version, self.tables, self.seed = out, version, tables, seed
        self.kind = kind
        self.index = index
        self.name = scene_name(index)
        self.keyframes = num_keyframes(seconds)
        self.world: World = scene_world(seed, index, seconds, kind)
        self.hw = tuple(int(v) for v in image_hw)
        self.cams = sensor_rig.cameras(self.hw)
        self.T_ego_lidar = sensor_rig.lidar_T_ego_from_lidar()
        self.t0_us = BASE_TIMESTAMP_US + (seed % 1000) * 10 ** 10 + index * 10 ** 9
        self.logfile = f"synth{seed}-{self.name}"
        self.scene_token = token(seed, "scene", index)
        self.log_token = token(seed, "log", index)
        self.chains = {ch: [] for ch in CAMERA_NAMES + ("LIDAR_TOP",)}
        self.samples = []
        self.ann_by_thing = {}
        self._setup_tables()

    # -- static records ------------------------------------------------------------------------
    def _setup_tables(self):
        T = self.tables
        map_token = token(self.seed, "map", self.index)
        T.add("log", {"token": self.log_token, "logfile": self.logfile, "vehicle": "synth-car",
                      "date_captured": "2018-08-01", "location": "synth-city"})
        T.add("map", {"token": map_token, "log_tokens": [self.log_token], "category": "semantic_prior",
                      "filename": f"maps/{map_token}.png"})
        os.makedirs(os.path.join(self.out, "maps"), exist_ok=True)
        Image.fromarray(np.zeros((1, 1), np.uint8)).save(os.path.join(self.out, "maps", f"{map_token}.png"))
        self.calib = {}
        for cam in self.cams:
            tok = token(self.seed, "calibrated_sensor", self.index, cam.name)
            T.add("calibrated_sensor", {
                "token": tok, "sensor_token": token("sensor", cam.name),
                "translation": [float(v) for v in cam.T_ego_from_cam[:3, 3]],
                "rotation": [float(v) for v in sensor_rig.CAMERA_CALIBRATION[cam.name][1]],
                "camera_intrinsic": [[float(v) for v in row] for row in cam.intrinsics]})
            self.calib[cam.name] = tok
        tok = token(self.seed, "calibrated_sensor", self.index, "LIDAR_TOP")
        T.add("calibrated_sensor", {"token": tok, "sensor_token": token("sensor", "LIDAR_TOP"),
                                    "translation": list(sensor_rig.LIDAR_CALIBRATION[0]),
                                    "rotation": list(sensor_rig.LIDAR_CALIBRATION[1]), "camera_intrinsic": []})
        self.calib["LIDAR_TOP"] = tok

    def stamp(self, t):
        return self.t0_us + int(round(t * 1e6))

    def _sample_data(self, channel, t, key, k, ext, height, width):
        ts = self.stamp(t)
        tok = token(self.seed, "sample_data", self.index, channel, ts)
        folder = "samples" if key else "sweeps"
        rec = {"token": tok, "sample_token": token(self.seed, "sample", self.index, k),
               "ego_pose_token": tok, "calibrated_sensor_token": self.calib[channel], "timestamp": ts,
               "fileformat": ext.split(".")[0], "is_key_frame": bool(key), "height": height, "width": width,
               "filename": f"{folder}/{channel}/{self.logfile}__{channel}__{ts}.{ext}", "prev": "", "next": ""}
        self.tables.add("sample_data", rec)
        self.tables.add("ego_pose", _pose_record(tok, ts, self.world.ego_pose(t)))
        self.chains[channel].append(rec)
        return rec

    # -- sensors -------------------------------------------------------------------------------------
    def camera_set(self, m, k, key):
        """Render camera set m (its six images at their own stamps). Returns keyframe data."""
        out = []
        for ci, cam in enumerate(self.cams):
            t, prims, hits, image = camera_image(self.world, self.seed, self.index, m, ci, cam,
                                                 self.hw)
            rec = self._sample_data(cam.name, t, key, k, "jpg", self.hw[0], self.hw[1])
            path = os.path.join(self.out, rec["filename"])
            os.makedirs(os.path.dirname(path), exist_ok=True)
            Image.fromarray(image).save(path, quality=90)
            if key:
                out.append((cam, t, hits, prims))
        return out

    def lidar_sweep(self, j, k, key):
        t = (j + 1) / sensor_rig.LIDAR_HZ   # stamped at the end of the rotation
        prims = self.world.prims_at(t)
        T_global_lidar = self.world.ego_pose(t) @ self.T_ego_lidar
        hits, dirs_g, dirs_l = sensors.scan_lidar(prims, T_global_lidar)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, self.index, 7919, j]))
        points, seg, inst = sensors.lidar_points(self.world, prims, hits, dirs_g, dirs_l, T_global_lidar[:3, 3], rng)
        rec = self._sample_data("LIDAR_TOP", t, key, k, "pcd.bin", 0, 0)
        path = os.path.join(self.out, rec["filename"])
        os.makedirs(os.path.dirname(path), exist_ok=True)
        points.tofile(path)
        return rec, t, prims, points, seg, inst

    # -- keyframe --------------------------------------------------------------------------------
    def keyframe(self, k, cam_data, lidar):
        lidar_rec, t, prims, points, seg, inst = lidar
        sample_token = token(self.seed, "sample", self.index, k)
        ts = self.stamp(t)
        self.samples.append({"token": sample_token, "timestamp": ts, "prev": "", "next": "",
                             "scene_token": self.scene_token})
        # lidarseg labels
        rel = f"lidarseg/{self.version}/{lidar_rec['token']}_lidarseg.bin"
        os.makedirs(os.path.join(self.out, os.path.dirname(rel)), exist_ok=True)
        seg.astype(np.uint8).tofile(os.path.join(self.out, rel))
        self.tables.add("lidarseg", {"token": lidar_rec["token"], "sample_data_token": lidar_rec["token"],
                                     "filename": rel})
        # Occ3D ground truth
        T_global_ego = self.world.ego_pose(t)
        sem = occupancy.voxelize(self.world, prims, T_global_ego)
        occupied = sem != occupancy.FREE_LABEL
        dist = np.linalg.norm(points[:, :3].astype(np.float64), axis=1)
        dirs = (points[:, :3] / np.maximum(dist, 1e-9)[:, None]) @ self.T_ego_lidar[:3, :3].T
        mask_lidar = occupancy.traverse(occupied, self.T_ego_lidar[:3, 3], dirs, dist, stop_at_occupied=False)
        mask_camera = np.zeros_like(mask_lidar)
        T_ego_global = invert_transform(T_global_ego)
        for cam, t_cam, _, prims_cam in cam_data:
            T_global_cam = self.world.ego_pose(t_cam) @ cam.T_ego_from_cam
            K, hw = mask_ray_grid(cam)
            depth, dirs = sensors.render_camera(prims_cam, T_global_cam, K, hw)
            R = T_ego_global[:3, :3]
            mask_camera |= occupancy.camera_mask(depth.t, depth.normal @ R.T, dirs @ R.T, K, hw,
                                                 T_ego_global @ T_global_cam)
        save_npz(os.path.join(self.out, "gts", self.name, sample_token, "labels.npz"), semantics=sem,
                 mask_lidar=mask_lidar.astype(np.uint8), mask_camera=mask_camera.astype(np.uint8))
        # annotations
        centre, yaw, wlh, vel = self.world.boxes(t)
        n_things = len(centre)
        lidar_pts = np.bincount(inst[inst >= 0], minlength=n_things)
        covered, visible = np.zeros(n_things), np.zeros(n_things)
        for _, _, hits, prims_c in cam_data:
            obj = hits.prim >= 0
            win_inst = prims_c.inst[hits.prim[obj]]
            visible += np.bincount(win_inst[win_inst >= 0], minlength=n_things)
            pi = prims_c.inst[hits.pair_prim]
            keep = pi >= 0
            key = np.unique(hits.pair_ray[keep] * (n_things + 1) + pi[keep])
            covered += np.bincount(key % (n_things + 1), minlength=n_things + 1)[:n_things]
        ego_xy = T_global_ego[:2, 3]
        near = np.flatnonzero(np.linalg.norm(centre[:, :2] - ego_xy, axis=1) < ANNOTATION_RANGE)
        speeds = np.linalg.norm(vel, axis=1)
        for i in near:
            rec = {"token": token(self.seed, "sample_annotation", self.index, k, i), "sample_token": sample_token,
                   "instance_token": token(self.seed, "instance", self.index, i),
                   "visibility_token": visibility_token(visible[i] / covered[i] if covered[i] else 0.0),
                   "attribute_tokens": [self.tables.attribute_token(a) for a in self._attributes(i, speeds[i])],
                   "translation": [float(v) for v in centre[i]], "size": [float(v) for v in wlh[i]],
                   "rotation": list(yaw_to_quaternion(yaw[i])), "prev": "", "next": "",
                   "num_lidar_pts": int(lidar_pts[i]), "num_radar_pts": 0}
            self.ann_by_thing.setdefault(i, []).append(rec)
            self.tables.add("sample_annotation", rec)

    def _attributes(self, i, speed):
        thing = self.world.things[i]
        if thing.kind == "pedestrian":
            return ["pedestrian.moving" if speed > 0.3 else "pedestrian.standing"]
        if thing.kind == "cycle":
            return [thing.shape.attribute or "cycle.with_rider"]
        if thing.kind == "vehicle":
            if speed > 0.3:
                return ["vehicle.moving"]
            parked = self.world.movers.paths[thing.mover].length < 0.1
            return ["vehicle.parked" if parked else "vehicle.stopped"]
        return []

    def write_previews(self, k):
        """preview_cameras.png and preview_bev.png of keyframe k, next to the tables."""
        sample_token = token(self.seed, "sample", self.index, k)
        images = {}
        for name in CAMERA_NAMES:
            rec = next(r for r in self.chains[name] if r["is_key_frame"] and r["sample_token"] == sample_token)
            images[name] = np.asarray(Image.open(os.path.join(self.out, rec["filename"])).convert("RGB"))
        pictures.camera_mosaic(images).save(os.path.join(self.out, "preview_cameras.png"))
        gt = np.load(os.path.join(self.out, "gts", self.name, sample_token, "labels.npz"))
        pictures.bev_image(gt["semantics"], gt["mask_camera"].astype(bool)).save(
            os.path.join(self.out, "preview_bev.png"))

    def finish(self):
        T = self.tables
        link_chain(self.samples)
        for s in self.samples:
            T.add("sample", s)
        for recs in self.chains.values():
            link_chain(recs)
        for i, recs in sorted(self.ann_by_thing.items()):
            link_chain(recs)
            T.add("instance", {"token": token(self.seed, "instance", self.index, i),
                               "category_token": T.category_token(self.world.things[i].shape.category),
                               "nbr_annotations": len(recs), "first_annotation_token": recs[0]["token"],
                               "last_annotation_token": recs[-1]["token"]})
        T.add("scene", {"token": self.scene_token, "log_token": self.log_token, "nbr_samples": len(self.samples),
                        "first_sample_token": self.samples[0]["token"], "last_sample_token": self.samples[-1]["token"],
                        "name": self.name,
                        "description": f"synthetic {self.kind.description}, seed {self.seed}"})


def generate(out: str, scenes: int = 8, seconds: float = 6.0, seed: int = 0, image_hw=DEFAULT_IMAGE_HW,
             version: str = "v1.0-trainval", progress: bool = True,
             kind: SceneKind = SceneKind()) -> dict:
    """Generate the dataset, every scene of ``kind``. Returns a summary (counts, seconds,
    bytes)."""
    if scenes < 1 or seconds <= 0:
        raise ValueError("need at least one scene and a positive duration")
    if os.path.exists(os.path.join(out, version)) and os.listdir(os.path.join(out, version)):
        raise FileExistsError(f"{os.path.join(out, version)} already exists; choose an empty --out")
    start = time.time()
    os.makedirs(out, exist_ok=True)
    tables = Tables(seed)
    for name in CAMERA_NAMES:
        tables.add("sensor", {"token": token("sensor", name), "channel": name, "modality": "camera"})
    tables.add("sensor", {"token": token("sensor", "LIDAR_TOP"), "channel": "LIDAR_TOP", "modality": "lidar"})
    keyframes = num_keyframes(seconds)
    bar = tqdm(total=scenes * keyframes, unit="keyframe", desc="odg synth", disable=not progress)
    names = []
    for i in range(scenes):
        w = _SceneWriter(out, version, tables, seed, i, seconds, image_hw, kind)
        names.append(w.name)
        cps, lps = sensor_rig.CAMERA_SETS_PER_KEYFRAME, sensor_rig.SWEEPS_PER_KEYFRAME
        for k in range(w.keyframes):
            cam_data = []
            for m in range(max(0, cps * (k - 1) + 1), cps * k + 1):
                cam_data = w.camera_set(m, k, key=(m == cps * k)) or cam_data
            lidar = None
            for j in range(max(0, lps * (k - 1) + 1), lps * k + 1):
                lidar = w.lidar_sweep(j, k, key=(j == lps * k))
            w.keyframe(k, cam_data, lidar)
            bar.set_postfix_str(w.name)
            bar.update(1)
        w.finish()
        if i == 0:
            w.write_previews(min(1, w.keyframes - 1))
    bar.close()
    tables.write(out, version)
    split = split_scenes(names)
    with open(os.path.join(out, "splits.json"), "w") as f:
        json.dump(split, f, indent=1)
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(out) for f in fs)
    images = sum(r["fileformat"] == "jpg" for r in tables.records["sample_data"])
    return {"scenes": scenes, "keyframes": scenes * keyframes, "images": images,
            "lidar_sweeps": len(tables.records["sample_data"]) - images,
            "seconds": time.time() - start, "bytes": size, "split": split}
