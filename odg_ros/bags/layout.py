"""The nuScenes ROS 2 bag layout: topic names, frames, message types and QoS (no rclpy).

One place for what ``odg bag`` writes, ``odg replay`` publishes and the node subscribes to by
default::

    /CAM_FRONT/image_rect_compressed  sensor_msgs/msg/CompressedImage  frame CAM_FRONT  best effort
    /CAM_FRONT/camera_info            sensor_msgs/msg/CameraInfo       frame CAM_FRONT  best effort
    ... the same for the other five cameras
    /LIDAR_TOP                        sensor_msgs/msg/PointCloud2      frame LIDAR_TOP  best effort
    /tf                               tf2_msgs/msg/TFMessage           map -> base_link  reliable
    /tf_static                        tf2_msgs/msg/TFMessage           base_link -> sensors
                                                                       reliable, transient local
    /odom                             nav_msgs/msg/Odometry            map, base_link  reliable

Camera frames are the nuScenes camera frames, i.e. optical frames (x right, y down, z forward),
so ``base_link -> CAM_*`` is the nuScenes ``calibrated_sensor`` pose as it is.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..nuscenes_cameras import CAMERA_NAMES

MAP_FRAME = "map"
BASE_FRAME = "base_link"
LIDAR_NAME = "LIDAR_TOP"

IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
TF_TYPE = "tf2_msgs/msg/TFMessage"
ODOM_TYPE = "nav_msgs/msg/Odometry"

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
ODOM_TOPIC = "/odom"
CLOCK_TOPIC = "/clock"
LIDAR_TOPIC = "/" + LIDAR_NAME


def image_topic(camera: str) -> str:
    return f"/{camera}/image_rect_compressed"


def camera_info_topic(camera: str) -> str:
    return f"/{camera}/camera_info"


@dataclass(frozen=True)
class TopicQos:
    """The QoS a topic is offered with (in the bag metadata and by ``odg replay``).

    reliable: RELIABLE, else BEST_EFFORT (sensor data). transient_local: late joiners get the
    last ``depth`` messages (``/tf_static``). History is always KEEP_LAST ``depth``.
    """
    reliable: bool
    transient_local: bool = False
    depth: int = 10


SENSOR_QOS = TopicQos(reliable=False, depth=5)
TF_QOS = TopicQos(reliable=True, depth=100)
TF_STATIC_QOS = TopicQos(reliable=True, transient_local=True, depth=1)
STATE_QOS = TopicQos(reliable=True, depth=50)


SENSOR_TYPES = (IMAGE_TYPE, CAMERA_INFO_TYPE, POINT_CLOUD_TYPE, "sensor_msgs/msg/Image")


def topic_qos(topic: str, msgtype: str | None = None) -> TopicQos:
    """QoS of a topic: /tf_static transient local, /tf reliable, camera images, camera infos
    and point clouds (by layout name or by message type) best effort, anything else reliable."""
    if topic == TF_STATIC_TOPIC:
        return TF_STATIC_QOS
    if topic == TF_TOPIC:
        return TF_QOS
    layout_sensor_topics = {LIDAR_TOPIC} | {image_topic(c) for c in CAMERA_NAMES} \
        | {camera_info_topic(c) for c in CAMERA_NAMES}
    if topic in layout_sensor_topics or msgtype in SENSOR_TYPES:
        return SENSOR_QOS
    return STATE_QOS
