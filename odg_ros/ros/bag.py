"""rosbag2 MCAP bags of nuScenes-format scenes, and a reader for them (rosbags; no rclpy).

``write_scene_bag`` writes one scene in the layout of ``bag_layout``: every camera image
(keyframes and sweeps, JPEG bytes as they are in the dataroot) with its CameraInfo, LiDAR
sweeps (optional), ``/tf`` and ``/odom`` at every ego pose, ``/tf_static`` once at the start.
Stamps are the nuScenes microsecond timestamps in nanoseconds; the bag's log time of every
message is its header stamp, and messages are written in time order (at equal stamps: poses
first, then calibration, then data), so ``ros2 bag play`` and ``odg replay`` give a consumer
the pose before the image it belongs to.

``iter_bag`` yields ``(topic, stamp_ns, msgtype, cdr_bytes)`` in log-time order.
"""
from __future__ import annotations

import shutil
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from odg_ros import geometry
from odg_ros.data.lidar import load_points
from odg_ros.ros import bag_layout as layout
from odg_ros.ros.nuscenes_source import LIDAR_CHANNEL, SensorRecord

# rosbag2 metadata version 8 is what ROS 2 Jazzy writes; later releases read it.
BAG_VERSION = 8
# Half-width of the central difference that gives /odom its twist: ego poses come every few
# milliseconds (one per sensor stamp), too close together for a stable finite difference.
TWIST_HALF_WINDOW_S = 0.1


@lru_cache(maxsize=1)
def typestore():
    """The rosbags type store for the standard ROS 2 messages (Jazzy definitions; the messages
    used here have the same definitions and type hashes from Humble to Kilted)."""
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def deserialize(raw: bytes, msgtype: str):
    """CDR bytes -> rosbags message object (for tests and tools)."""
    return typestore().deserialize_cdr(raw, msgtype)


# ---------------------------------------------------------------------------------------------
# Odometry twist from poses


def _nearest(t: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Index of the element of sorted ``t`` nearest to each target (ties: the earlier one)."""
    right = np.clip(np.searchsorted(t, targets), 1, len(t) - 1)
    left = right - 1
    return np.where(targets - t[left] <= t[right] - targets, left, right)


def ego_twists(times_us, T_global_from_ego) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame twist at each pose by central differences over about +-0.1 s.

    times_us: int [N] strictly increasing; T_global_from_ego: [N, 4, 4].
    Returns (linear [N, 3] m/s, angular [N, 3] rad/s), both in the ego (base_link) frame at
    pose i, as nav_msgs/Odometry wants (twist in child_frame_id). Poses a and b around i are
    the ones nearest to t_i -+ 0.1 s (clipped to the ends); v = R_i^T (p_b - p_a) / dt and
    w = log(R_a^T R_b) / dt. A single pose gets zero twist.
    """
    t = np.asarray(times_us, dtype=np.float64) * 1e-6
    T = np.asarray(T_global_from_ego, dtype=np.float64)
    n = len(t)
    if T.shape != (n, 4, 4):
        raise ValueError(f"poses {T.shape} do not match {n} stamps")
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(t))):
        raise ValueError("non-finite ego pose or stamp")
    if n > 1 and np.any(np.diff(t) <= 0):
        raise ValueError("pose stamps must be strictly increasing")
    linear = np.zeros((n, 3))
    angular = np.zeros((n, 3))
    if n < 2:
        return linear, angular
    index = np.arange(n)
    a = np.minimum(_nearest(t, t - TWIST_HALF_WINDOW_S), index - (index > 0))  # >= 1 step back
    b = np.maximum(_nearest(t, t + TWIST_HALF_WINDOW_S), index + (index < n - 1))
    dt = t[b] - t[a]
    R = T[:, :3, :3]
    v_global = (T[b, :3, 3] - T[a, :3, 3]) / dt[:, None]
    linear = np.einsum("nji,nj->ni", R, v_global)
    R_rel = np.einsum("nji,njk->nik", R[a], R[b])
    angular = Rotation.from_matrix(R_rel).as_rotvec() / dt[:, None]
    return linear, angular


# ---------------------------------------------------------------------------------------------
# Message construction (rosbags types)


def _stamp(timestamp_ns: int):
    Time = typestore().types["builtin_interfaces/msg/Time"]
    return Time(sec=int(timestamp_ns // 1_000_000_000), nanosec=int(timestamp_ns % 1_000_000_000))


def _header(timestamp_ns: int, frame_id: str):
    Header = typestore().types["std_msgs/msg/Header"]
    return Header(stamp=_stamp(timestamp_ns), frame_id=frame_id)


def _pose_parts(T):
    """4x4 -> (translation xyz, quaternion as ROS x, y, z, w)."""
    w, x, y, z = geometry.matrix_to_quaternion(np.asarray(T)[:3, :3])
    return np.asarray(T)[:3, 3], (x, y, z, w)


def _transform_stamped(timestamp_ns, parent, child, T):
    types = typestore().types
    (tx, ty, tz), (qx, qy, qz, qw) = _pose_parts(T)
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(timestamp_ns, parent), child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
            rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))


def tf_message(transforms):
    return typestore().types[layout.TF_TYPE](transforms=list(transforms))


def odometry_message(timestamp_ns, T_global_from_ego, linear, angular):
    types = typestore().types
    (px, py, pz), (qx, qy, qz, qw) = _pose_parts(T_global_from_ego)
    Vector3 = types["geometry_msgs/msg/Vector3"]
    return types[layout.ODOM_TYPE](
        header=_header(timestamp_ns, layout.MAP_FRAME), child_frame_id=layout.BASE_FRAME,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=px, y=py, z=pz),
                orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)),
            covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](
                linear=Vector3(x=float(linear[0]), y=float(linear[1]), z=float(linear[2])),
                angular=Vector3(x=float(angular[0]), y=float(angular[1]), z=float(angular[2]))),
            covariance=np.zeros(36)))


def camera_info_message(timestamp_ns, camera, intrinsics, width, height):
    """Rectified pinhole camera: no distortion, R = I, P = [K | 0]."""
    K = np.asarray(intrinsics, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    types = typestore().types
    return types[layout.CAMERA_INFO_TYPE](
        header=_header(timestamp_ns, camera), height=int(height), width=int(width),
        distortion_model="plumb_bob", d=np.zeros(5), k=K.reshape(-1), r=np.eye(3).reshape(-1),
        p=P.reshape(-1), binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                      do_rectify=False))


def compressed_image_message(timestamp_ns, camera, data: bytes, image_format="jpeg"):
    return typestore().types[layout.IMAGE_TYPE](
        header=_header(timestamp_ns, camera), format=image_format,
        data=np.frombuffer(data, dtype=np.uint8))


POINT_FIELDS = ("x", "y", "z", "intensity", "ring")


def point_cloud_message(timestamp_ns, frame_id, points):
    """float32 [P, 5] (x, y, z, intensity, ring) -> PointCloud2 with five FLOAT32 fields."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != len(POINT_FIELDS):
        raise ValueError(f"points must be [P, {len(POINT_FIELDS)}], got {points.shape}")
    types = typestore().types
    PointField = types["sensor_msgs/msg/PointField"]
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate(POINT_FIELDS)]
    return types[layout.POINT_CLOUD_TYPE](
        header=_header(timestamp_ns, frame_id), height=1, width=len(points), fields=fields,
        is_bigendian=False, point_step=4 * len(POINT_FIELDS),
        row_step=4 * len(POINT_FIELDS) * len(points),
        data=points.view(np.uint8).reshape(-1), is_dense=True)


# ---------------------------------------------------------------------------------------------
# Writing


def _rosbags_qos(qos: layout.TopicQos):
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
        _transform_stamped(start_ns, layout.BASE_FRAME, channel, T)
        for channel, T in sorted(statics.items()))

    last_pose_stamp = None
    for r in records:
        stamp_ns = int(r.timestamp_us) * 1000
        if r.timestamp_us != last_pose_stamp:
            last_pose_stamp = r.timestamp_us
            T = pose_by_stamp[r.timestamp_us]
            yield layout.TF_TOPIC, stamp_ns, tf_message(
                [_transform_stamped(stamp_ns, layout.MAP_FRAME, layout.BASE_FRAME, T)])
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
                        offered_qos_profiles=[_rosbags_qos(layout.topic_qos(topic))])
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


# ---------------------------------------------------------------------------------------------
# Reading


@dataclass(frozen=True)
class BagTopic:
    name: str
    msgtype: str
    count: int
    qos: layout.TopicQos | None  # the offered QoS recorded in the bag, None when absent


def bag_topics(path) -> dict[str, BagTopic]:
    """Topics of a rosbag2 bag (any storage rosbags reads) with their recorded QoS."""
    from rosbags.interfaces import QosDurability, QosReliability
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as reader:
        result = {}
        for conn in reader.connections:
            profiles = getattr(conn.ext, "offered_qos_profiles", None) or []
            qos = None
            if profiles:
                p = profiles[0]
                qos = layout.TopicQos(
                    reliable=p.reliability != QosReliability.BEST_EFFORT,
                    transient_local=p.durability == QosDurability.TRANSIENT_LOCAL,
                    depth=max(1, int(p.depth or 1)))
            previous = result.get(conn.topic)
            count = conn.msgcount + (previous.count if previous else 0)
            result[conn.topic] = BagTopic(conn.topic, conn.msgtype, count, qos)
        return result


def iter_bag(path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, str, bytes]]:
    """Yield ``(topic, log_time_ns, msgtype, cdr_bytes)`` of a bag in log-time order."""
    from rosbags.rosbag2 import Reader

    wanted = None if topics is None else set(topics)
    with Reader(Path(path)) as reader:
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not connections:
            return
        for conn, timestamp, raw in reader.messages(connections=connections):
            yield conn.topic, int(timestamp), conn.msgtype, bytes(raw)
