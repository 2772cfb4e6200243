"""Bags of one nuScenes-format world in the layouts of the public nuScenes -> ROS converters
(docs/bags.md), for the layout tests. Our own code, written from the converters' published
layouts as far as they matter to the node: topic names, message types, frame ids, stamps, log
times, what is missing. Topics the node never reads (LiDAR and radar clouds, maps, markers,
GPS, IMU) are left out, except one marker topic of a custom type in the Foxglove-derived
layout (a player must skip what it cannot publish).

* ``odg``: ``odg bag`` (odg_ros/bags/writer.py).
* ``foxglove``: the ROS 2 port of Foxglove's nuscenes2mcap (``nuscenes_to_ros2bag``). MCAP,
  no QoS recorded. Per keyframe (sample), all logged at the sample's LiDAR time: the CAN
  ``/odom`` (50 Hz, map -> base_link) and ``/diagnostics`` stamped since the previous
  keyframe, ``/tf`` with ``map -> base_link`` and ``base_link -> every sensor`` for this
  sample and the next (all dynamic, no /tf_static), the keyframe image of each camera
  (``/CAM_X/image_rect_compressed``, JPEG bytes as on disk, frame ``CAM_X``, stamped with its
  own time) with its CameraInfo (R = [1,0,0, 1,0,0, 1,0,0], D empty, no distortion model);
  then the sweeps up to the next keyframe at their own times. Nothing before the first
  keyframe.
* ``chris7462``: Chris7462/nuscenes_to_ros2bag. MCAP. Every sample_data in time order, logged
  at its stamp: ``/nuscenes/cam_x/image_raw`` (``Image`` bgr8, the JPEG decoded with OpenCV
  as cv::imread does, frame ``cam_x_link``, offered best effort) with
  ``/nuscenes/cam_x/camera_info`` (D empty, R = I, reliable), then ``/nuscenes/odom`` (the
  ego pose at that stamp, map -> base_link, no twist). No TF.
* ``nuscenes2bag``: clynamen/nuscenes2bag (ROS 1), converted to rosbag2 with rosbags'
  converter as ``rosbags-convert --src N.bag --dst N`` does (SQLite 3). Per ego pose (one per
  sample_data): ``/odom`` (odom -> base_link) and ``/tf`` (``odom -> base_link``,
  ``base_link -> cam_x`` and the LiDAR, ``map -> odom`` identity, all at that stamp; the ROS 1
  ``tf/tfMessage`` becomes ``tf2_msgs/msg/TFMessage``); images on ``cam_x/raw`` (no leading
  slash; ``Image`` bgr8, frame ``cam_x``). No CameraInfo, no /tf_static.

``reselect_keyframes`` makes a world whose keyframe gaps are longer than 0.5 s by choosing
other keyframes among the same sensor data.
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import cv2
import numpy as np

from odg_ros.bags import bag_messages as bag_messages
from odg_ros.bags.nuscenes_source import LIDAR_CHANNEL, SensorRecord
from odg_ros.bags.writer import rosbags_qos, write_scene_bag
from odg_ros.online.poses import interpolate_pose
from odg_ros.nuscenes_cameras import CAMERA_NAMES

LAYOUTS = ("odg", "foxglove", "chris7462", "nuscenes2bag")
CAN_HZ = 50
CUSTOM_MARKER_TYPE = "foxglove_msgs/msg/ImageMarkerArray"


# ---------------------------------------------------------------------------------------------
# Worlds


def keyframe_groups(records: list[SensorRecord]) -> list[dict[str, SensorRecord]]:
    """The samples of a scene: channel -> its keyframe record, the k-th keyframe of every
    channel (the LiDAR's stamp is the sample's)."""
    keys: dict[str, list[SensorRecord]] = {}
    for r in records:
        if r.is_key_frame:
            keys.setdefault(r.channel, []).append(r)
    if LIDAR_CHANNEL not in keys:
        raise ValueError("the layouts need the LiDAR keyframes (scene_records with_lidar)")
    count = min(len(v) for v in keys.values())
    return [{channel: rs[k] for channel, rs in keys.items()} for k in range(count)]


def reselect_keyframes(records: list[SensorRecord], gaps: list[float]) -> list[SensorRecord]:
    """The same sensor data with other keyframes, ``gaps`` seconds apart (nuScenes picks a
    LiDAR sweep about every 0.5 s; its gaps scatter around that: scene-0061 has one of
    0.550 s): the last LiDAR sweep is the last keyframe, the others lie the gaps before it
    (each must fall on a sweep), and the keyframe images are the camera set nearest to the
    middle of the keyframe sweep (nuScenes triggers each camera as the LiDAR passes its view;
    the synthetic LiDAR, stamped at the end of its turn, has a camera set only every fifth
    sweep, so other keyframes take the nearest set). Stamps and poses stay: the car drives on
    as before."""
    lidar = [r for r in records if r.channel == LIDAR_CHANNEL]
    stamps = [lidar[-1].timestamp_us]
    for gap in reversed(gaps):
        stamps.insert(0, stamps[0] - int(round(gap * 1e6)))
    by_stamp = {r.timestamp_us: r for r in lidar}
    missing = [s for s in stamps if s not in by_stamp]
    if missing:
        raise ValueError(f"no LiDAR sweep at {missing} us: the gaps must be multiples of the "
                         "sweep period")
    half_sweep = (lidar[-1].timestamp_us - lidar[-2].timestamp_us) // 2
    images = {c: [r for r in records if r.channel == c] for c in CAMERA_NAMES}
    keys = {id(by_stamp[s]) for s in stamps}
    for s in stamps:
        front = min(images[CAMERA_NAMES[0]], key=lambda r: abs(r.timestamp_us - s + half_sweep))
        for channel in CAMERA_NAMES:
            keys.add(id(min(images[channel],
                            key=lambda r: abs(r.timestamp_us - front.timestamp_us))))
    return [dataclasses.replace(r, is_key_frame=id(r) in keys) for r in records]


def keyframe_pose_records(records: list[SensorRecord]) -> list[SensorRecord]:
    """The same world with only the ego poses that /tf at keyframes carries: each record's
    ego pose interpolated between the keyframe poses around it (linear position, slerp
    rotation, as tf2 interpolates); outside the keyframes' span (nothing there to
    interpolate) the record keeps its pose. Written by ``odg bag``, it carries the same
    information as the Foxglove-derived layout without /odom."""
    keys = [(g[LIDAR_CHANNEL].timestamp_us, g[LIDAR_CHANNEL].T_global_from_ego)
            for g in keyframe_groups(records)]
    stamps = np.array([t for t, _ in keys], dtype=np.int64)
    out = []
    for r in records:
        i = int(np.searchsorted(stamps, r.timestamp_us))
        if 0 < i < len(stamps):
            (t0, T0), (t1, T1) = keys[i - 1], keys[i]
            r = dataclasses.replace(r, T_global_from_ego=interpolate_pose(
                t0 * 1e-6, T0, t1 * 1e-6, T1, r.timestamp_us * 1e-6))
        out.append(r)
    return out


def keyframe_gaps(records: list[SensorRecord]) -> list[float]:
    stamps = [g[LIDAR_CHANNEL].timestamp_us for g in keyframe_groups(records)]
    return [round((b - a) * 1e-6, 6) for a, b in zip(stamps, stamps[1:])]


def write_layout_bag(layout: str, records: list[SensorRecord], out) -> Path:
    """The world's records as a bag of ``layout`` at ``out`` (a rosbag2 folder)."""
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    if layout == "odg":
        write_scene_bag([r for r in records if r.channel != LIDAR_CHANNEL], out,
                        progress=False)
    elif layout == "foxglove":
        _write_foxglove(records, out)
    elif layout == "chris7462":
        _write_chris7462(records, out)
    elif layout == "nuscenes2bag":
        _write_nuscenes2bag(records, out)
    else:
        raise ValueError(f"unknown layout {layout!r}")
    return out


# ---------------------------------------------------------------------------------------------
# Messages the odg layout does not need


def _types():
    return bag_messages.typestore().types


def decoded_bgr(path: Path) -> np.ndarray:
    """A camera JPEG as the C++ converters read it: cv::imread(path, IMREAD_COLOR)."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise FileNotFoundError(path)
    return image


def raw_image_message(stamp_ns: int, frame: str, bgr: np.ndarray):
    """sensor_msgs/Image bgr8 as cv_bridge makes it from an OpenCV image."""
    height, width = bgr.shape[:2]
    return _types()["sensor_msgs/msg/Image"](
        header=bag_messages._header(stamp_ns, frame), height=height, width=width,
        encoding="bgr8", is_bigendian=0, step=3 * width,
        data=np.ascontiguousarray(bgr).reshape(-1))


def camera_info_message(stamp_ns: int, frame: str, K, width: int, height: int, *,
                        r_wrong: bool):
    """CameraInfo as the converters write it: D empty, no distortion model, P = [K | 0];
    R = I, or (r_wrong) with ones at indices 0, 3 and 6 as the Foxglove-derived one sets it."""
    K = np.asarray(K, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    R = np.zeros(9)
    R[[0, 3, 6] if r_wrong else [0, 4, 8]] = 1.0
    types = _types()
    return types["sensor_msgs/msg/CameraInfo"](
        header=bag_messages._header(stamp_ns, frame), height=int(height), width=int(width),
        distortion_model="", d=np.zeros(0), k=K.reshape(-1), r=R, p=P.reshape(-1),
        binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                      width=0, do_rectify=False))


def odometry(stamp_ns: int, parent: str, T, linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0)):
    msg = bag_messages.odometry_message(stamp_ns, T, linear, angular)
    msg.header.frame_id = parent
    return msg


def diagnostics_message(stamp_ns: int, speed: float):
    types = _types()
    status = types["diagnostic_msgs/msg/DiagnosticStatus"](
        level=0, name="Zoe Vehicle Info", message="OK",
        hardware_id="",
        values=[types["diagnostic_msgs/msg/KeyValue"](key="speed", value=f"{speed:.4f}")])
    return types["diagnostic_msgs/msg/DiagnosticArray"](
        header=bag_messages._header(stamp_ns, ""), status=[status])


def _with_custom_marker_type():
    """A type store that also knows foxglove_msgs/msg/ImageMarkerArray (not available to
    rclpy)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg("visualization_msgs/ImageMarker[] markers",
                                      CUSTOM_MARKER_TYPE))
    return store


class _Bag:
    """A rosbags rosbag2 writer that adds connections as topics first appear."""

    def __init__(self, out: Path, storage: str = "mcap", qos=None, store=None):
        from rosbags.rosbag2 import StoragePlugin, Writer
        if out.exists():
            shutil.rmtree(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        self.store = store or bag_messages.typestore()
        self.qos = qos or {}
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self.writer = Writer(out, version=8, storage_plugin=plugin)
        self.connections = {}

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()
        return False

    def write(self, topic: str, log_ns: int, msg) -> None:
        if topic not in self.connections:
            profiles = [rosbags_qos(self.qos[topic])] if topic in self.qos else []
            self.connections[topic] = self.writer.add_connection(
                topic, msg.__msgtype__, typestore=self.store, offered_qos_profiles=profiles)
        self.writer.write(self.connections[topic], int(log_ns),
                          self.store.serialize_cdr(msg, msg.__msgtype__))


def _ns(record: SensorRecord) -> int:
    return int(record.timestamp_us) * 1000


# ---------------------------------------------------------------------------------------------
# The Foxglove-derived ROS 2 converter


def can_poses(records: list[SensorRecord]) -> list[tuple[int, np.ndarray]]:
    """The CAN bus pose at 50 Hz over the scene, (stamp us, T_global_from_ego), from the
    ego poses of the sample_data (interpolated between the nearest two)."""
    stamps = np.array([r.timestamp_us for r in records], dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    poses = [records[i].T_global_from_ego for i in order]
    out = []
    for t in range(int(stamps[0]), int(stamps[-1]) + 1, 1_000_000 // CAN_HZ):
        i = int(np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1))
        if stamps[i] == stamps[i - 1]:
            out.append((t, poses[i]))
        else:
            out.append((t, interpolate_pose(stamps[i - 1] * 1e-6, poses[i - 1],
                                            stamps[i] * 1e-6, poses[i], t * 1e-6)))
    return out


def _sample_transforms(group: dict[str, SensorRecord]) -> list:
    lidar = group[LIDAR_CHANNEL]
    stamp = _ns(lidar)
    transforms = [bag_messages.transform_stamped(stamp, "map", "base_link",
                                                 lidar.T_global_from_ego)]
    for channel in [LIDAR_CHANNEL] + list(CAMERA_NAMES):
        if channel in group:
            transforms.append(bag_messages.transform_stamped(
                stamp, "base_link", channel, group[channel].T_ego_from_sensor))
    return transforms


def _write_foxglove(records: list[SensorRecord], out: Path) -> None:
    groups = keyframe_groups(records)
    can = can_poses(records)
    can_stamps = np.array([t for t, _ in can], dtype=np.int64)
    linear, angular = bag_messages.ego_twists(can_stamps, np.stack([T for _, T in can]))
    by_channel: dict[str, list[SensorRecord]] = {}
    for r in records:
        by_channel.setdefault(r.channel, []).append(r)
    next_can = 0
    with _Bag(out, store=_with_custom_marker_type()) as bag:
        for k, group in enumerate(groups):
            t_k = _ns(group[LIDAR_CHANNEL])
            # CAN stamped before this keyframe, logged now
            while next_can < len(can) and can[next_can][0] * 1000 < t_k:
                stamp = can[next_can][0] * 1000
                bag.write("/odom", t_k, odometry(stamp, "map", can[next_can][1],
                                                  linear[next_can], angular[next_can]))
                bag.write("/diagnostics", t_k,
                          diagnostics_message(stamp, float(np.linalg.norm(linear[next_can]))))
                next_can += 1
            transforms = _sample_transforms(group)
            if k + 1 < len(groups):
                transforms += _sample_transforms(groups[k + 1])
            bag.write("/tf", t_k, bag_messages.tf_message(transforms))
            for channel in CAMERA_NAMES:
                if channel in group:
                    _write_foxglove_camera(bag, group[channel], t_k)
                    bag.write(f"/{channel}/image_markers_annotations", t_k,
                              bag.store.types[CUSTOM_MARKER_TYPE](markers=[]))
            # the sweeps after this keyframe, up to the next, at their own times
            sweeps = []
            for channel in CAMERA_NAMES:
                chain = by_channel.get(channel, [])
                if channel not in group:
                    continue
                i = chain.index(group[channel]) + 1
                while i < len(chain) and not chain[i].is_key_frame:
                    sweeps.append(chain[i])
                    i += 1
            for r in sorted(sweeps, key=lambda r: r.timestamp_us):
                _write_foxglove_camera(bag, r, _ns(r))


def _write_foxglove_camera(bag: _Bag, r: SensorRecord, log_ns: int) -> None:
    stamp = _ns(r)
    bag.write(f"/{r.channel}/image_rect_compressed", log_ns,
              bag_messages.compressed_image_message(stamp, r.channel, r.path.read_bytes()))
    height, width = decoded_bgr(r.path).shape[:2] if not r.width else (r.height, r.width)
    bag.write(f"/{r.channel}/camera_info", log_ns,
              camera_info_message(stamp, r.channel, r.intrinsics, width, height,
                                  r_wrong=True))


# ---------------------------------------------------------------------------------------------
# Chris7462/nuscenes_to_ros2bag


def _write_chris7462(records: list[SensorRecord], out: Path) -> None:
    from odg_ros.bags.layout import TopicQos
    sensor = TopicQos(reliable=False, depth=5)
    reliable = TopicQos(reliable=True, depth=10)
    qos = {"/nuscenes/odom": reliable}
    for channel in CAMERA_NAMES:
        qos[f"/nuscenes/{channel.lower()}/image_raw"] = sensor
        qos[f"/nuscenes/{channel.lower()}/camera_info"] = reliable
    with _Bag(out, qos=qos) as bag:
        for r in sorted(records, key=lambda r: r.timestamp_us):
            stamp = _ns(r)
            name = r.channel.lower()
            if r.channel != LIDAR_CHANNEL:      # the LiDAR cloud itself: left out
                bgr = decoded_bgr(r.path)
                bag.write(f"/nuscenes/{name}/image_raw", stamp,
                          raw_image_message(stamp, f"{name}_link", bgr))
                bag.write(f"/nuscenes/{name}/camera_info", stamp,
                          camera_info_message(stamp, f"{name}_link", r.intrinsics,
                                              bgr.shape[1], bgr.shape[0], r_wrong=False))
            bag.write("/nuscenes/odom", stamp, odometry(stamp, "map", r.T_global_from_ego))


# ---------------------------------------------------------------------------------------------
# clynamen/nuscenes2bag (ROS 1) + rosbags-convert


def _ros1_typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS1_NOETIC)
    if "tf/msg/tfMessage" not in store.types:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                          "tf/msg/tfMessage"))
    return store


def _ros1_header(types, stamp_ns: int, frame: str):
    return types["std_msgs/msg/Header"](
        seq=0, stamp=types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000,
                                                          nanosec=stamp_ns % 1_000_000_000),
        frame_id=frame)


def _ros1_transform(types, stamp_ns, parent, child, T):
    return types["geometry_msgs/msg/TransformStamped"](
        header=_ros1_header(types, stamp_ns, parent), child_frame_id=child,
        transform=bag_messages.ros_transform(types, T))


def _ros1_odometry(types, stamp_ns, T):
    zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return types["nav_msgs/msg/Odometry"](
        header=_ros1_header(types, stamp_ns, "odom"), child_frame_id="base_link",
        pose=bag_messages.pose_with_covariance(types, T),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
            covariance=np.zeros(36)))


def write_nuscenes2bag_ros1(records: list[SensorRecord], path: Path) -> Path:
    """The ROS 1 bag as nuscenes2bag writes it: every ego pose (/odom, /tf) first, then the
    images (a ROS 1 bag is read back in time order)."""
    from rosbags.rosbag1 import Writer
    store = _ros1_typestore()
    types = store.types
    statics = {}
    for r in records:
        statics.setdefault(r.channel, r.T_ego_from_sensor)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    writer = Writer(path)
    connections = {}

    def write(topic, stamp, msg):
        if topic not in connections:
            connections[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=store)
        writer.write(connections[topic], stamp, store.serialize_ros1(msg, msg.__msgtype__))

    with writer:
        for r in records:                      # one ego pose per sample_data
            stamp = _ns(r)
            write("/odom", stamp, _ros1_odometry(types, stamp, r.T_global_from_ego))
            transforms = [_ros1_transform(types, stamp, "odom", "base_link",
                                          r.T_global_from_ego)]
            transforms += [_ros1_transform(types, stamp, "base_link", channel.lower(), T)
                           for channel, T in sorted(statics.items())]
            transforms.append(_ros1_transform(types, stamp, "map", "odom", np.eye(4)))
            write("/tf", stamp, types["tf/msg/tfMessage"](transforms=transforms))
        for r in records:
            if r.channel == LIDAR_CHANNEL:     # the LiDAR cloud itself: left out
                continue
            stamp = _ns(r)
            bgr = decoded_bgr(r.path)
            height, width = bgr.shape[:2]
            name = r.channel.lower()
            write(f"{name}/raw", stamp, types["sensor_msgs/msg/Image"](
                header=_ros1_header(types, stamp, name), height=height, width=width,
                encoding="bgr8", is_bigendian=0, step=3 * width,
                data=np.ascontiguousarray(bgr).reshape(-1)))
    return path


def _write_nuscenes2bag(records: list[SensorRecord], out: Path) -> None:
    from rosbags.convert import convert
    ros1 = out.parent / f"{out.name}.bag"
    write_nuscenes2bag_ros1(records, ros1)
    if out.exists():
        shutil.rmtree(out)
    # what `rosbags-convert --src N.bag --dst N` does (its defaults: SQLite 3, version 9)
    convert(srcs=[ros1], dst=out, dst_storage="sqlite3", dst_version=9, compress=None,
            compress_mode="file", default_typestore=None, typestore=None, exclude_topics=[],
            include_topics=[], exclude_msgtypes=[], include_msgtypes=[])


# ---------------------------------------------------------------------------------------------
# The layout tests' world


@dataclasses.dataclass
class LayoutWorld:
    """One synthetic scene with keyframe gaps of 0.55 and 0.75 s, as a bag of every layout
    (and ``odg keyframe poses``: ``odg bag`` of the world with only its keyframe poses,
    keyframe_pose_records), with rig files of its car for the layouts that need one."""

    root: Path
    records: list[SensorRecord]
    bags: dict[str, Path]
    rigs: dict[str, Path]

    def camera_sets_us(self, every: int = 1) -> list[int]:
        """Reference (CAM_FRONT) stamps of the camera sets from the first keyframe on (the
        Foxglove-derived layout writes nothing before it), every ``every``-th."""
        front = [r for r in self.records if r.channel == "CAM_FRONT"]
        first = next(r.timestamp_us for r in front if r.is_key_frame)
        return [r.timestamp_us for r in front if r.timestamp_us >= first][::every]


GAPS = [0.55, 0.75]


def build_layout_world(root: Path, seconds: float = 2.0, image_hw=(45, 80)) -> LayoutWorld:
    from odg_ros.bags.converters import CONVERTERS
    from odg_ros.bags.nuscenes_source import NuScenesSensorTables
    from odg_ros.bags.rig_file import write_rig_file
    from odg_ros.data.synth.generate import generate

    root = Path(root)
    generate(str(root / "world"), scenes=1, seconds=seconds, image_hw=image_hw, progress=False)
    tables = NuScenesSensorTables(root / "world")
    records = reselect_keyframes(tables.scene_records("scene-0001"), GAPS)
    bags = {layout: write_layout_bag(layout, records, root / "bags" / layout)
            for layout in LAYOUTS}
    bags["odg keyframe poses"] = write_layout_bag("odg", keyframe_pose_records(records),
                                                  root / "bags" / "odg_keyframe_poses")
    rigs = {name: write_rig_file(records, CONVERTERS[name], "scene-0001",
                                 root / f"rig_{name}.yaml")
            for name in ("odg", "chris7462", "nuscenes2bag")}
    return LayoutWorld(root, records, bags, rigs)
