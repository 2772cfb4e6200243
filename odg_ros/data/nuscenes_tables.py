"""Read the nuScenes v1.0 JSON tables of a dataroot (real nuScenes or ``odg synth``) without
the devkit: token lookup, keyframe sample_data per channel, annotations per sample, poses.

Field names and links follow the nuScenes schema (nuscenes-devkit's README): ``sample_data``
points at ``calibrated_sensor`` (-> ``sensor.channel``) and ``ego_pose``; keyframe
sample_data carry ``is_key_frame`` and the ``sample_token`` of their sample; per-channel
``prev``/``next`` chains link all sample_data of a scene in time.
"""
from __future__ import annotations

import json
import os

import numpy as np

from ..classes import BOX_CLASSES
from ..geometry import make_transform

REQUIRED_TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor",
                   "sample_annotation", "instance", "category", "log")
OPTIONAL_TABLES = ("attribute", "visibility", "map")

# nuScenes general category -> detection class (the nuScenes detection benchmark's mapping);
# every other category has no box class.
CATEGORY_TO_BOX_CLASS = {
    "vehicle.car": "car", "vehicle.truck": "truck", "vehicle.construction": "construction_vehicle",
    "vehicle.bus.bendy": "bus", "vehicle.bus.rigid": "bus", "vehicle.trailer": "trailer",
    "movable_object.barrier": "barrier", "vehicle.motorcycle": "motorcycle", "vehicle.bicycle": "bicycle",
    "human.pedestrian.adult": "pedestrian", "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian", "human.pedestrian.police_officer": "pedestrian",
    "movable_object.trafficcone": "traffic_cone",
}
assert set(CATEGORY_TO_BOX_CLASS.values()) == set(BOX_CLASSES)


def pose_matrix(record) -> np.ndarray:
    """4x4 from a record with ``rotation`` (w, x, y, z) and ``translation``."""
    return make_transform(np.asarray(record["rotation"], float), np.asarray(record["translation"], float))


class NuScenesTables:
    """The tables of ``<dataroot>/<version>/*.json`` indexed by token."""

    def __init__(self, dataroot, version="v1.0-trainval"):
        self.dataroot = str(dataroot)
        self.version = version
        root = os.path.join(self.dataroot, version)
        if not os.path.isdir(root):
            raise FileNotFoundError(f"no nuScenes tables at {root} (wrong --dataroot or --version?)")
        self.tables = {}
        for name in REQUIRED_TABLES:
            path = os.path.join(root, f"{name}.json")
            if not os.path.exists(path):
                raise FileNotFoundError(f"missing nuScenes table {path}")
            with open(path) as f:
                self.tables[name] = json.load(f)
        for name in OPTIONAL_TABLES:
            path = os.path.join(root, f"{name}.json")
            if os.path.exists(path):
                with open(path) as f:
                    self.tables[name] = json.load(f)
        path = os.path.join(root, "lidarseg.json")
        self.lidarseg = {}
        if os.path.exists(path):
            with open(path) as f:
                self.lidarseg = {r["sample_data_token"]: r["filename"] for r in json.load(f)}
        self.index = {name: {r["token"]: r for r in records} for name, records in self.tables.items()}
        channel_of_calib = {c["token"]: self.index["sensor"][c["sensor_token"]]["channel"]
                            for c in self.tables["calibrated_sensor"]}
        self.channel = {sd["token"]: channel_of_calib[sd["calibrated_sensor_token"]]
                        for sd in self.tables["sample_data"]}
        self.keyframe_data = {}   # sample token -> {channel: sample_data record}
        for sd in self.tables["sample_data"]:
            if sd["is_key_frame"]:
                self.keyframe_data.setdefault(sd["sample_token"], {})[self.channel[sd["token"]]] = sd
        self.annotations = {}     # sample token -> [sample_annotation]
        for ann in self.tables["sample_annotation"]:
            self.annotations.setdefault(ann["sample_token"], []).append(ann)

    def get(self, table, token) -> dict:
        try:
            return self.index[table][token]
        except KeyError:
            raise KeyError(f"{table} token {token!r} not found in {self.dataroot}/{self.version}") from None

    def scenes(self) -> list[dict]:
        return sorted(self.tables["scene"], key=lambda s: s["name"])

    def scene_samples(self, scene) -> list[dict]:
        """The scene's samples in time order (following ``next`` from the first)."""
        out, tok = [], scene["first_sample_token"]
        while tok:
            sample = self.get("sample", tok)
            out.append(sample)
            tok = sample["next"]
        return out

    def category_name(self, annotation) -> str:
        instance = self.get("instance", annotation["instance_token"])
        return self.get("category", instance["category_token"])["name"]

    def ego_pose(self, sample_data) -> np.ndarray:
        """T_global_from_ego at the sample_data's stamp."""
        return pose_matrix(self.get("ego_pose", sample_data["ego_pose_token"]))

    def calibration(self, sample_data) -> dict:
        return self.get("calibrated_sensor", sample_data["calibrated_sensor_token"])

    def annotation_velocity(self, annotation, max_time_diff=1.5) -> np.ndarray:
        """Global velocity [3] of an annotation as nuscenes-devkit's ``box_velocity`` computes it:
        centred difference of the neighbouring annotations of the same instance (one-sided at
        the ends) over their samples' time difference; NaN when it cannot be estimated or the
        time difference exceeds ``max_time_diff`` (doubled for a centred difference)."""
        has_prev, has_next = annotation["prev"] != "", annotation["next"] != ""
        if not has_prev and not has_next:
            return np.full(3, np.nan)
        first = self.get("sample_annotation", annotation["prev"]) if has_prev else annotation
        last = self.get("sample_annotation", annotation["next"]) if has_next else annotation
        dt = 1e-6 * (self.get("sample", last["sample_token"])["timestamp"]
                     - self.get("sample", first["sample_token"])["timestamp"])
        if has_prev and has_next:
            max_time_diff *= 2
        if dt > max_time_diff or dt <= 0:
            return np.full(3, np.nan)
        return (np.asarray(last["translation"], float) - np.asarray(first["translation"], float)) / dt
