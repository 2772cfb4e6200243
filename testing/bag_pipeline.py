"""A bag through the node's ROS-free pipeline, deterministically (no DDS, no timing): the
messages in the order a player publishes them, converted as odg_node converts them, and every
complete camera set run once the bag has been read ``defer_s`` past its stamp (what the
node's bounded wait for a late pose does in real time; here nothing is dropped as stale), so
two bags of one world can be compared grid for grid.

The wiring follows odg_ros/ros/node.py (pose_sources, on_image, on_camera_info, on_odometry,
on_tf) without rclpy: CDR is decoded with rosbags.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from odg_ros.bags.messages import deserialize
from odg_ros.bags.reader import open_bag
from odg_ros.online.errors import BadInput
from odg_ros.online.images import EncodedImage
from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings
from odg_ros.online.poses import pose_from_xyz_xyzw
from odg_ros.online.rig import Rig
from odg_ros.online.transforms import TransformBuffer


@dataclass
class Settings:
    """The node parameters a layout sets (names as in config/odg_node.schema.yaml).
    intrinsics_source rig: the cameras' intrinsics and image sizes come from ``rig``, not from
    CameraInfo (a layout without CameraInfo)."""

    camera_names: list[str]
    image_topic: str = "/{camera}/image_rect_compressed"
    camera_info_topic: str = "/{camera}/camera_info"
    pose_source: str = "tf"
    odometry_topic: str = "/odom"
    global_frame: str = "map"
    base_frame: str = "base_link"
    extrinsics_source: str = "rig"
    intrinsics_source: str = "camera_info"
    rig: Rig | None = None
    slop: float = 0.05
    max_pose_extrapolation: float = 0.05


VARIANTS = ("odg", "foxglove", "foxglove tf", "chris7462", "nuscenes2bag")


def layout_settings(world, variant: str) -> Settings:
    """The documented settings of each layout (config/bags/*.yaml; "foxglove tf":
    foxglove_tf.yaml) for a LayoutWorld (testing/bag_layouts.py), as pipeline settings."""
    from odg_ros.bags.converters import CONVERTERS
    from odg_ros.online.rig import load_rig
    from odg_ros.resources import resource_path

    lower = CONVERTERS["chris7462"].camera_names()
    upper = CONVERTERS["odg"].camera_names()
    if variant == "odg":
        return Settings(upper, rig=load_rig(resource_path("config/rig_nuscenes.yaml")))
    if variant == "foxglove":
        return Settings(upper, pose_source="odometry", extrinsics_source="tf")
    if variant == "foxglove tf":
        return Settings(upper, extrinsics_source="tf")
    if variant == "chris7462":
        return Settings(lower, image_topic="/nuscenes/{camera}/image_raw",
                        camera_info_topic="/nuscenes/{camera}/camera_info",
                        pose_source="odometry", odometry_topic="/nuscenes/odom",
                        extrinsics_source="rig", rig=load_rig(world.rigs["chris7462"]))
    if variant == "nuscenes2bag":
        return Settings(lower, image_topic="/{camera}/raw", extrinsics_source="tf",
                        intrinsics_source="rig", rig=load_rig(world.rigs["nuscenes2bag"]))
    raise ValueError(f"unknown layout variant {variant!r} (one of {', '.join(VARIANTS)})")


@dataclass
class BagRun:
    grids: dict[int, np.ndarray] = field(default_factory=dict)   # reference stamp us -> labels
    skipped: Counter = field(default_factory=Counter)             # BadInput kind -> sets
    messages: int = 0


def _stamp(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def _transform(tf) -> np.ndarray:
    t, r = tf.transform.translation, tf.transform.rotation
    return pose_from_xyz_xyzw((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))


def run_bag(bag_path, predictor, s: Settings, defer_s: float = 1.0,
            only_us: set[int] | None = None) -> BagRun:
    """Every camera set of the bag (or those whose reference stamp in microseconds is in
    ``only_us``; the others are passed over, as stale sets are) through a fresh pipeline
    around ``predictor`` (its history starts empty: give each run a new OnlinePredictor)."""
    bag_time = [0.0]      # the TF cache ages with the bag, not with the time a step takes
    tf = TransformBuffer(max_extrapolation=s.max_pose_extrapolation,
                         clock=lambda: bag_time[0])
    pose_lookup = None
    if s.pose_source == "tf":
        pose_lookup = lambda t: tf.lookup(s.global_frame, s.base_frame, t, "pose_miss")  # noqa
    if s.extrinsics_source == "rig":
        extrinsics = lambda camera, frame_id, t: s.rig.cameras[camera].sensor2ego  # noqa
    else:
        extrinsics = lambda camera, frame_id, t: tf.lookup(  # noqa
            s.base_frame, frame_id, t, "missing_extrinsics")
    pipeline = OnlinePipeline(predictor, PipelineSettings(
        s.camera_names, slop=s.slop, pose_max_extrapolation=s.max_pose_extrapolation),
        extrinsics, pose_lookup)
    images = {s.image_topic.format(camera=c): c for c in s.camera_names}
    infos = {s.camera_info_topic.format(camera=c): c for c in s.camera_names}
    if s.intrinsics_source == "rig":
        infos = {}
        for camera in s.camera_names:
            calibration = s.rig.cameras[camera]
            pipeline.on_camera_info(camera, calibration.intrinsics, *calibration.image_hw,
                                    calibration.frame_id)
    run = BagRun()
    waiting = []     # complete sets not run yet
    bag = open_bag(bag_path)
    try:
        for topic, log_ns, msgtype, raw in bag.messages():
            name = topic if topic.startswith("/") else "/" + topic     # as a player resolves
            now = bag_time[0] = log_ns * 1e-9
            run.messages += 1
            try:
                _feed(pipeline, tf, s, images, infos, name, msgtype, raw, now)
            except BadInput as error:
                run.skipped[error.kind] += 1
            while True:
                camera_set = pipeline.next_set(timeout=0)
                if camera_set is None:
                    break
                waiting.append(camera_set)
            while waiting and waiting[0].reference_stamp + defer_s <= now:
                _process(pipeline, waiting.pop(0), run, only_us)
        for camera_set in waiting:
            _process(pipeline, camera_set, run, only_us)
    finally:
        pipeline.close()
    return run


def _feed(pipeline, tf, s: Settings, images, infos, topic, msgtype, raw, now) -> None:
    if topic in images:
        msg = deserialize(raw, msgtype)
        if msgtype.endswith("CompressedImage"):
            image = EncodedImage(True, msg.format, msg.data.tobytes())
        else:
            image = EncodedImage(False, msg.encoding, msg.data.tobytes(), msg.height,
                                 msg.width, msg.step)
        pipeline.on_image(images[topic], _stamp(msg.header), image, now)
    elif topic in infos:
        msg = deserialize(raw, msgtype)
        pipeline.on_camera_info(infos[topic], np.asarray(msg.k), msg.height, msg.width,
                                msg.header.frame_id)
    elif s.pose_source == "odometry" and topic == s.odometry_topic:
        msg = deserialize(raw, msgtype)
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        pipeline.on_pose(_stamp(msg.header), pose_from_xyz_xyzw((p.x, p.y, p.z),
                                                                (o.x, o.y, o.z, o.w)))
    elif topic in ("/tf", "/tf_static") and (s.pose_source == "tf"
                                             or s.extrinsics_source == "tf"):
        for transform in deserialize(raw, msgtype).transforms:
            tf.add(transform.header.frame_id, transform.child_frame_id,
                   _stamp(transform.header), _transform(transform), topic == "/tf_static")


def _process(pipeline, camera_set, run: BagRun, only_us) -> None:
    if only_us is not None and int(round(camera_set.reference_stamp * 1e6)) not in only_us:
        return
    try:
        result = pipeline.process(camera_set)
    except BadInput as error:
        run.skipped[error.kind] += 1
        return
    run.grids[int(round(result.stamp * 1e6))] = result.grid
