"""A bag through the node's ROS-free pipeline, deterministically (no DDS, no timing): the
messages in the order a player publishes them, converted as odg_node converts them, the node's
clock at each message's log time (``use_sim_time`` with ``--clock``), and after every message
each camera set that is ready (or whose bounded wait ran out, in bag time) run at once: a node
with an infinitely fast model. Two bags of one world can then be compared grid for grid.

The node's parameters come from a layout's params file (config/bags/*.yaml, as docs/bags.md
gives them), validated against the schema, and the TF buffer, the extrinsics, the intrinsics
of a rig file and the pipeline are built by odg_ros/online/node_setup.py, as odg_node builds
them: the same max_pose_gap, pose_wait, extrinsics_source, intrinsics_source... The message
wiring follows odg_ros/ros/node.py (on_image, on_camera_info, on_odometry, on_tf) without
rclpy: CDR is decoded with rosbags.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from odg_ros.bags.bag_messages import deserialize
from odg_ros.bags.reader import open_bag
from odg_ros.online import node_setup
from odg_ros.online.errors import BadInput
from odg_ros.online.images import EncodedImage
from odg_ros.online.parameters import params_file_parameters, validate
from odg_ros.online.poses import pose_from_xyz_xyzw
from odg_ros.resources import resource_path

# layout variant -> (its params file, the bag of LayoutWorld.bags it reads, rig file needed)
VARIANTS = {
    "odg": ("config/odg.yaml", "odg", False),
    # the world with only its keyframe poses (the reference of "foxglove tf")
    "odg keyframe poses": ("config/odg.yaml", "odg keyframe poses", False),
    "foxglove": ("config/bags/foxglove.yaml", "foxglove", False),
    "foxglove tf": ("config/bags/foxglove_tf.yaml", "foxglove", False),
    "chris7462": ("config/bags/chris7462.yaml", "chris7462", True),
    "nuscenes2bag": ("config/bags/nuscenes2bag.yaml", "nuscenes2bag", True),
}


def layout_parameters(world, variant: str, **overrides) -> dict:
    """The node's validated parameters for a layout variant of a LayoutWorld
    (testing/bag_layouts.py): its documented params file, the world's rig file where the
    layout needs one (as `odg bag rig` writes it), then ``overrides``."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown layout variant {variant!r} (one of {', '.join(VARIANTS)})")
    params_file, bag, needs_rig = VARIANTS[variant]
    values = params_file_parameters(resource_path(params_file))
    if needs_rig:
        values["rig_file"] = str(world.rigs[bag])
    values.update(overrides)
    return validate(values)


def variant_bag(world, variant: str) -> Path:
    return world.bags[VARIANTS[variant][1]]


@dataclass
class BagRun:
    grids: dict[int, np.ndarray] = field(default_factory=dict)   # reference stamp us -> labels
    skipped: Counter = field(default_factory=Counter)             # BadInput kind -> sets
    counters: dict = field(default_factory=dict)                  # the pipeline's, at the end
    messages: int = 0


def _stamp(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def _transform(tf) -> np.ndarray:
    t, r = tf.transform.translation, tf.transform.rotation
    return pose_from_xyz_xyzw((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))


def run_bag(bag_path, predictor, p: dict, only_us: set[int] | None = None,
            flush_s: float = 5.0) -> BagRun:
    """Every camera set of the bag (or those whose reference stamp in microseconds is in
    ``only_us``; the others are passed over, as stale sets are) through a fresh pipeline
    around ``predictor`` (its history starts empty: give each run a new OnlinePredictor),
    with the node's validated parameters ``p``. After the last message the bag clock runs
    on ``flush_s`` so that sets still waiting are taken or expire."""
    bag_time = [0.0]      # the node's clock: the log time of the message being read
    cameras = list(p["camera_names"])
    found = node_setup.sources(p, cameras, clock=lambda: bag_time[0])
    pipeline = node_setup.build_pipeline(predictor, p, cameras, found,
                                         clock=lambda: bag_time[0])
    images = {p["image_topic"].format(camera=c): c for c in cameras}
    infos = {} if p["intrinsics_source"] == "rig" else \
        {p["camera_info_topic"].format(camera=c): c for c in cameras}
    wiring = _Wiring(pipeline, found.tf, p, images, infos, clock=lambda: bag_time[0])
    run = BagRun()
    bag = open_bag(bag_path)
    try:
        for topic, log_ns, msgtype, raw in bag.messages():
            name = topic if topic.startswith("/") else "/" + topic     # as a player resolves
            bag_time[0] = log_ns * 1e-9
            run.messages += 1
            try:
                wiring.feed(name, msgtype, raw)
            except BadInput as error:
                run.skipped[error.kind] += 1
            _take_ready_sets(pipeline, run, only_us)
        bag_time[0] += flush_s
        _take_ready_sets(pipeline, run, only_us)
        run.counters = pipeline.counters()
    finally:
        pipeline.close()
    return run


class _Wiring:
    """odg_node's callbacks, on messages decoded from the bag."""

    def __init__(self, pipeline, tf, p: dict, images: dict, infos: dict, clock):
        self.pipeline, self.tf, self.p, self.clock = pipeline, tf, p, clock
        self.images, self.infos = images, infos
        self.tf_topics = ("/tf", "/tf_static") if p["pose_source"] == "tf" or \
            p["extrinsics_source"] != "rig" else ()

    def feed(self, topic: str, msgtype: str, raw) -> None:
        pipeline, now = self.pipeline, self.clock()
        if topic in self.images:
            msg = deserialize(raw, msgtype)
            if msgtype.endswith("CompressedImage"):
                image = EncodedImage(True, msg.format, msg.data.tobytes())
            else:
                image = EncodedImage(False, msg.encoding, msg.data.tobytes(), msg.height,
                                     msg.width, msg.step)
            pipeline.on_image(self.images[topic], _stamp(msg.header), image, now)
        elif topic in self.infos:
            msg = deserialize(raw, msgtype)
            pipeline.on_camera_info(self.infos[topic], np.asarray(msg.k), msg.height,
                                    msg.width, msg.header.frame_id)
        elif self.p["pose_source"] == "odometry" and topic == self.p["odometry_topic"]:
            msg = deserialize(raw, msgtype)
            position, orientation = msg.pose.pose.position, msg.pose.pose.orientation
            pipeline.on_pose(_stamp(msg.header), pose_from_xyz_xyzw(
                (position.x, position.y, position.z),
                (orientation.x, orientation.y, orientation.z, orientation.w)))
        elif topic in self.tf_topics:
            for transform in deserialize(raw, msgtype).transforms:
                self.tf.add(transform.header.frame_id, transform.child_frame_id,
                            _stamp(transform.header), _transform(transform),
                            topic == "/tf_static")
            pipeline.transforms_arrived()


def _take_ready_sets(pipeline, run: BagRun, only_us) -> None:
    """Every set the waiting room hands on now (ready, failed or expired), run at once; one
    passed over (not in ``only_us``) is still looked up if its wait ran out, so that a miss
    is counted wherever it falls."""
    while (camera_set := pipeline.next_set(timeout=0)) is not None:
        chosen = only_us is None or int(round(camera_set.reference_stamp * 1e6)) in only_us
        try:
            if chosen:
                result = pipeline.process(camera_set)
                run.grids[int(round(result.stamp * 1e6))] = result.grid
            elif camera_set.expired:
                pipeline.prepare(camera_set)
        except BadInput as error:
            run.skipped[error.kind] += 1
