"""ROS 2 messages of a bag as rosbags objects (no rclpy): TF, odometry with a twist derived
from the poses, CameraInfo, CompressedImage, PointCloud2, and CDR (de)serialisation."""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.spatial.transform import Rotation

from .. import geometry
from . import layout

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


def ros_transform(types, T):
    """geometry_msgs/Transform of a 4x4 transform, from the message classes ``types`` (a
    typestore's, ROS 2 or ROS 1)."""
    (tx, ty, tz), (qx, qy, qz, qw) = _pose_parts(T)
    return types["geometry_msgs/msg/Transform"](
        translation=types["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
        rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))


def transform_stamped(timestamp_ns, parent, child, T):
    types = typestore().types
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(timestamp_ns, parent), child_frame_id=child,
        transform=ros_transform(types, T))


def tf_message(transforms):
    return typestore().types[layout.TF_TYPE](transforms=list(transforms))


def pose_with_covariance(types, T):
    """geometry_msgs/PoseWithCovariance of a 4x4 pose, covariance zeros (not given), from the
    message classes ``types`` (a typestore's, ROS 2 or ROS 1)."""
    (px, py, pz), (qx, qy, qz, qw) = _pose_parts(T)
    return types["geometry_msgs/msg/PoseWithCovariance"](
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=px, y=py, z=pz),
            orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)),
        covariance=np.zeros(36))


def odometry_message(timestamp_ns, T_global_from_ego, linear, angular):
    types = typestore().types
    Vector3 = types["geometry_msgs/msg/Vector3"]
    return types[layout.ODOM_TYPE](
        header=_header(timestamp_ns, layout.MAP_FRAME), child_frame_id=layout.BASE_FRAME,
        pose=pose_with_covariance(types, T_global_from_ego),
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
