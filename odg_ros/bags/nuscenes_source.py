"""Read one scene of a nuScenes-format dataroot as time-ordered sensor records (no rclpy).

Only what a bag needs: for every camera and LiDAR ``sample_data`` of a scene (keyframes AND
sweeps) its channel, microsecond stamp, file, ego pose at that stamp and the sensor's
calibration. Tables used (``<dataroot>/<version>/*.json``, the nuScenes schema): scene,
sample, sample_data, ego_pose, calibrated_sensor, sensor. A sweep belongs to the scene of the
sample its ``sample_token`` names (as in the nuScenes devkit). Narrower than
odg_ros.data.nuscenes_tables (the training-side reader): no annotation tables are needed, so
it also bags datasets or splits without them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import geometry
from ..nuscenes_cameras import CAMERA_NAMES
from .layout import LIDAR_NAME

LIDAR_CHANNEL = LIDAR_NAME
TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")


@dataclass(frozen=True)
class SensorRecord:
    """One camera image or LiDAR sweep with the poses that go with it.

    T_global_from_ego and T_ego_from_sensor are 4x4 float64 (odg_ros.geometry conventions);
    intrinsics is 3x3 for cameras, None for the LiDAR; width/height 0 when unknown.
    """
    channel: str
    timestamp_us: int
    path: Path
    is_key_frame: bool
    ego_pose_token: str
    T_global_from_ego: np.ndarray
    T_ego_from_sensor: np.ndarray
    intrinsics: np.ndarray | None
    width: int
    height: int


def find_version(dataroot: Path) -> str:
    """The one ``v1.0-*``-style folder of ``dataroot`` that holds the tables."""
    dataroot = Path(dataroot)
    if not dataroot.is_dir():
        raise FileNotFoundError(f"dataroot not found: {dataroot}")
    versions = sorted(p.name for p in dataroot.iterdir() if (p / "scene.json").is_file())
    if len(versions) != 1:
        found = ", ".join(versions) if versions else "none"
        raise ValueError(f"{dataroot}: expected exactly one folder with scene.json "
                         f"(found: {found}); pass --version")
    return versions[0]


class NuScenesSensorTables:
    """The sensor tables of one nuScenes version, indexed by token."""

    def __init__(self, dataroot, version: str | None = None):
        self.dataroot = Path(dataroot)
        self.version = version or find_version(self.dataroot)
        folder = self.dataroot / self.version
        if not folder.is_dir():
            raise FileNotFoundError(f"nuScenes version folder not found: {folder}")
        self.tables = {}
        for name in TABLES:
            path = folder / f"{name}.json"
            if not path.is_file():
                raise FileNotFoundError(f"nuScenes table missing: {path}")
            with open(path) as f:
                rows = json.load(f)
            if not isinstance(rows, list):
                raise ValueError(f"{path}: expected a JSON list of records")
            self.tables[name] = {row["token"]: row for row in rows}
        self._by_scene: dict[str, list[dict]] | None = None

    def scene_names(self) -> list[str]:
        return sorted(row["name"] for row in self.tables["scene"].values())

    def _scene(self, name: str) -> dict:
        for row in self.tables["scene"].values():
            if row["name"] == name:
                return row
        raise KeyError(f"scene {name!r} not in {self.dataroot / self.version} "
                       f"(scenes: {', '.join(self.scene_names())})")

    def _sample_data_by_scene(self) -> dict[str, list[dict]]:
        """scene token -> its sample_data rows (one pass over the table, then cached: the full
        nuScenes has millions of rows and bagging every scene must not rescan them)."""
        if self._by_scene is None:
            scene_of_sample = {tok: row["scene_token"] for tok, row in self.tables["sample"].items()}
            self._by_scene = {}
            for row in self.tables["sample_data"].values():
                scene_token = scene_of_sample.get(row["sample_token"])
                if scene_token is None:
                    raise ValueError(f"sample_data {row['token']} names unknown sample "
                                     f"{row['sample_token']}")
                self._by_scene.setdefault(scene_token, []).append(row)
        return self._by_scene

    def scene_records(self, scene_name: str, with_lidar: bool = True) -> list[SensorRecord]:
        """All camera (and LiDAR) sample_data of a scene, sorted by (stamp, channel)."""
        scene = self._scene(scene_name)
        rows = self._sample_data_by_scene().get(scene["token"], [])
        if not rows:
            raise ValueError(f"scene {scene_name!r} has no sample_data")
        channels = set(CAMERA_NAMES) | ({LIDAR_CHANNEL} if with_lidar else set())
        calib_cache: dict[str, tuple] = {}
        records = []
        for row in rows:
            calib_token = row["calibrated_sensor_token"]
            if calib_token not in calib_cache:
                calib = self.tables["calibrated_sensor"][calib_token]
                channel = self.tables["sensor"][calib["sensor_token"]]["channel"]
                T = geometry.make_transform(calib["rotation"], calib["translation"])
                K = calib.get("camera_intrinsic") or None
                K = np.asarray(K, dtype=np.float64) if K else None
                calib_cache[calib_token] = (channel, T, K)
            channel, T_ego_from_sensor, K = calib_cache[calib_token]
            if channel not in channels:
                continue
            if channel != LIDAR_CHANNEL and (K is None or K.shape != (3, 3)):
                raise ValueError(f"camera {channel} calibration {calib_token} has no 3x3 "
                                 "intrinsics")
            pose = self.tables["ego_pose"][row["ego_pose_token"]]
            records.append(SensorRecord(
                channel=channel,
                timestamp_us=int(row["timestamp"]),
                path=self.dataroot / row["filename"],
                is_key_frame=bool(row.get("is_key_frame", False)),
                ego_pose_token=row["ego_pose_token"],
                T_global_from_ego=geometry.make_transform(pose["rotation"], pose["translation"]),
                T_ego_from_sensor=T_ego_from_sensor,
                intrinsics=K,
                width=int(row.get("width") or 0),
                height=int(row.get("height") or 0),
            ))
        if not any(r.channel in CAMERA_NAMES for r in records):
            raise ValueError(f"scene {scene_name!r} has no camera images")
        records.sort(key=lambda r: (r.timestamp_us, r.channel))
        return records
