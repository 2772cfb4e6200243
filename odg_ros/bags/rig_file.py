"""The camera rig of one nuScenes scene as a rig file (the format of config/rig_nuscenes.yaml):
the calibrated_sensor records of its six cameras, under the camera names and frame ids of a
bag layout (odg_ros.bags.converters).

A bag that carries no camera extrinsics (Chris7462's converter) or no CameraInfo (nuscenes2bag)
needs the calibration of the car that recorded it; nuScenes logs come from several cars, so
the shipped rig (one car's) is right for some scenes only.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from .. import geometry
from ..nuscenes_cameras import CAMERA_NAMES
from .converters import Converter
from .nuscenes_source import SensorRecord


def _image_hw(record: SensorRecord) -> tuple[int, int]:
    if record.width > 0 and record.height > 0:
        return record.height, record.width
    with Image.open(record.path) as image:      # reads the header only
        return image.size[1], image.size[0]


def _numbers(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def rig_yaml(records: list[SensorRecord], converter: Converter, source: str) -> str:
    """The rig file text of a scene's records (NuScenesSensorTables.scene_records): the
    first record of each camera gives its calibration (odg bag refuses a scene whose
    calibration changes). ``source`` names where it comes from, for the header comment."""
    first = {}
    for record in records:
        if record.channel in CAMERA_NAMES and record.channel not in first:
            first[record.channel] = record
    missing = [c for c in CAMERA_NAMES if c not in first]
    if missing:
        raise ValueError(f"{source}: no images of {', '.join(missing)}")
    lines = [f"# Camera rig of {source} for bags written by {converter.title}",
             f"# (odg bag rig --layout {converter.name}); format: config/rig_nuscenes.yaml.",
             "base_frame: base_link", "cameras:"]
    for channel in CAMERA_NAMES:
        record = first[channel]
        T = record.T_ego_from_sensor
        if not geometry.is_rigid(T):
            raise ValueError(f"{source}: {channel} extrinsics are not a rigid transform")
        height, width = _image_hw(record)
        K = np.asarray(record.intrinsics, dtype=np.float64)
        lines += [f"  {converter.camera_name(channel)}:",
                  f"    frame_id: {converter.frame_id(channel)}",
                  f"    image_size: [{height}, {width}]",
                  "    intrinsics:"]
        lines += [f"      - {_numbers(row)}" for row in K]
        lines += ["    sensor2ego:",
                  f"      translation: {_numbers(T[:3, 3])}",
                  f"      rotation: {_numbers(geometry.matrix_to_quaternion(T[:3, :3]))}"]
    return "\n".join(lines) + "\n"


def write_rig_file(records: list[SensorRecord], converter: Converter, source: str, out,
                   force: bool = False) -> Path:
    out = Path(out)
    if out.exists() and not force:
        raise FileExistsError(f"{out} already exists (pass --force to replace it)")
    text = rig_yaml(records, converter, source)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return out
