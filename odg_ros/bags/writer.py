"""Write one nuScenes-format scene as a rosbag2 MCAP bag (rosbags; no rclpy).

``write_scene_bag`` writes one scene in the layout of ``odg_ros.bags.layout``: every camera
image (keyframes and sweeps, JPEG bytes as they are in the dataroot) with its CameraInfo, LiDAR
sweeps (optional), ``/tf`` and ``/odom`` at every ego pose, ``/tf_static`` once at the start.
Stamps are the nuScenes microsecond timestamps in nanoseconds; the bag's log time of every
message is its header stamp, and messages are written in time order (at equal stamps: poses
first, then calibration, then data), so ``ros2 bag play`` and ``odg replay`` give a consumer
the pose before the image it belongs to.
"""
from __future__ import annotations

import shutil
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .. import geometry
from ..data.lidar import load_points
from . import layout
from .bag_messages import (camera_info_message, compressed_image_message, ego_twists, odometry_message,
                       point_cloud_message, tf_message, transform_stamped, typestore)
from .nuscenes_source import LIDAR_CHANNEL, SensorRecord

# rosbag2 metadata version 8 is what ROS 2 Jazzy writes; later releases read it.
BAG_VERSION = 8


def rosbags_qos(qos: layout.TopicQos):
    """A layout QoS as the rosbags Qos recorded with a connection (offered_qos_profiles)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=qos.depth,
               reliability=QosReliability.RELIABLE if qos.reliable else QosReliability.BEST_EFFORT,
               durability=(QosDurability.TRANSIENT_LOCAL if qos.transient_local
                           else QosDurability.VOLATILE),
               deadline=zero, lifespan=zero, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=zero, avoid_ros_namespace_conventions=False)


def _image_size(record: SensorRecord) -> tuple[int, int]:
    if record.width > 0 and record.height > 0:
        return record.width, record.height
    from PIL import Image
    with Image.open(record.path) as image:  # reads the header only
        return image.size


def _read_bytes(path: Path) -> bytes:
    if not path.is_file():
        raise FileNotFoundError(f"sensor file not found: {path}")
    return path.read_bytes()


@dataclass
class BagSummary:
    path: Path
    counts: dict[str, int]
    start_ns: int
    end_ns: int

    def __str__(self) -> str:
        lines = [f"{self.path}: {sum(self.counts.values())} messages, "
                 f"{(self.end_ns - self.start_ns) * 1e-9:.2f} s"]
        lines += [f"  {topic:<40} {n:6d}" for topic, n in sorted(self.counts.items())]
        return "\n".join(lines)


def _scene_messages(records: list[SensorRecord]) -> Iterator[tuple[str, int, object]]:
    """(topic, stamp_ns, rosbags message) in write order (see the module docstring)."""
    # Ego poses: one per distinct stamp (nuScenes keeps one ego_pose per sample_data).
    pose_by_stamp = {}
    for r in records:
        pose_by_stamp.setdefault(r.timestamp_us, r.T_global_from_ego)
    pose_stamps = np.array(sorted(pose_by_stamp), dtype=np.int64)
    poses = np.stack([pose_by_stamp[s] for s in pose_stamps])
    for T in poses:
        if not geometry.is_rigid(T):
            raise ValueError("an ego pose is not a rigid transform")
    linear, angular = ego_twists(pose_stamps, poses)
    twist_of = {int(s): (linear[i], angular[i]) for i, s in enumerate(pose_stamps)}

    # Static transforms: the first calibration seen for each sensor (fixed within a scene).
    statics = {}
    for r in records:
        if r.channel in statics:
            if not np.allclose(statics[r.channel], r.T_ego_from_sensor, atol=1e-6):
                raise ValueError(f"{r.channel}: calibration changes within the scene; "
                                 "/tf_static cannot represent that")
            continue
        if not geometry.is_rigid(r.T_ego_from_sensor):
            raise ValueError(f"{r.channel}: sensor extrinsics are not a rigid transform")
        statics[r.channel] = r.T_ego_from_sensor
    start_ns = int(records[0].timestamp_us) * 1000
    yield layout.TF_STATIC_TOPIC, start_ns, tf_message(
        transform_stamped(start_ns, layout.BASE_FRAME, channel, T)
        for channel, T in sorted(statics.items()))

    last_pose_stamp = None
    for r in records:
        stamp_ns = int(r.timestamp_us) * 1000
        if r.timestamp_us != last_pose_stamp:
            last_pose_stamp = r.timestamp_us
            T = pose_by_stamp[r.timestamp_us]
            yield layout.TF_TOPIC, stamp_ns, tf_message(
                [transform_stamped(stamp_ns, layout.MAP_FRAME, layout.BASE_FRAME, T)])
            yield layout.ODOM_TOPIC, stamp_ns, odometry_message(stamp_ns, T,
                                                                *twist_of[r.timestamp_us])
        if r.channel == LIDAR_CHANNEL:
            yield layout.LIDAR_TOPIC, stamp_ns, point_cloud_message(stamp_ns, r.channel,
                                                                    load_points(r.path))
        else:
            width, height = _image_size(r)
            yield layout.camera_info_topic(r.channel), stamp_ns, camera_info_message(
                stamp_ns, r.channel, r.intrinsics, width, height)
            image_format = "png" if r.path.suffix.lower() == ".png" else "jpeg"
            yield layout.image_topic(r.channel), stamp_ns, compressed_image_message(
                stamp_ns, r.channel, _read_bytes(r.path), image_format)


def write_scene_bag(records: list[SensorRecord], out, *, force: bool = False,
                    progress: bool = True) -> BagSummary:
    """Write one scene's records (``NuScenesSensorTables.scene_records``) as an MCAP bag at ``out``.

    ``out`` must not exist, unless ``force`` and it is a bag folder (has metadata.yaml), which
    is then replaced. A failure leaves no partial bag behind.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    if not records:
        raise ValueError("no sensor records to write")
    out = Path(out)
    if out.exists():
        if not (force and (out / "metadata.yaml").is_file()):
            hint = " (pass --force to replace it)" if (out / "metadata.yaml").is_file() else ""
            raise FileExistsError(f"{out} already exists{hint}")
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    store = typestore()
    connections = {}
    counts: Counter = Counter()
    first_ns = last_ns = None
    try:
        with Writer(out, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
            bar = tqdm(total=len(records), desc=f"bag {out.name}", unit="file",
                       disable=not progress)
            for topic, stamp_ns, msg in _scene_messages(records):
                if topic not in connections:
                    connections[topic] = writer.add_connection(
                        topic, msg.__msgtype__, typestore=store,
                        offered_qos_profiles=[rosbags_qos(layout.topic_qos(topic))])
                writer.write(connections[topic], stamp_ns,
                             store.serialize_cdr(msg, msg.__msgtype__))
                counts[topic] += 1
                first_ns = stamp_ns if first_ns is None else first_ns
                last_ns = stamp_ns
                if msg.__msgtype__ in (layout.IMAGE_TYPE, layout.POINT_CLOUD_TYPE):
                    bar.update(1)  # one per sensor record
            bar.close()
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return BagSummary(path=out, counts=dict(counts), start_ns=first_ns, end_ns=last_ns)
