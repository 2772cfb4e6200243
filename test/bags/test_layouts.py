"""The layout fixtures say what docs/bags.md says of each converter (no rclpy): topics, types,
frames, stamps against log times, CameraInfo quirks, what is missing; `odg bag rig` names
cameras and frames as each layout does; the params files of config/bags/ set only parameters
the node knows (or is about to: those names are listed here)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from odg_ros.bags.converters import CONVERTERS
from odg_ros.bags.bag_messages import deserialize
from odg_ros.bags.reader import bag_topics, open_bag
from odg_ros.online.parameters import load_schema
from odg_ros.online.camera_calibration import load_rig
from odg_ros.resources import resource_path
from odg_ros.nuscenes_cameras import CAMERA_NAMES
from testing.bag_layouts import GAPS, keyframe_gaps, keyframe_groups

ROOT = Path(__file__).resolve().parents[2]
# Parameters the params files use that this release's node does not have yet: the pose
# interpolation bound and wait (max_pose_gap, pose_wait; also extrinsics_source: auto) and
# intrinsics from the rig file (intrinsics_source).
PENDING = {"max_pose_gap", "pose_wait", "intrinsics_source"}


def stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def messages(bag, topics=None):
    for topic, log_ns, msgtype, raw in open_bag(bag).messages(topics):
        yield topic, log_ns, deserialize(raw, msgtype)


def test_the_world_has_the_keyframe_gaps(layout_world):
    assert keyframe_gaps(layout_world.records) == GAPS


def test_foxglove_layout(layout_world):
    bag = layout_world.bags["foxglove"]
    topics = bag_topics(bag)
    assert all(t.qos is None for t in topics.values())          # no QoS recorded
    assert "/tf_static" not in topics
    for camera in CAMERA_NAMES:
        assert topics[f"/{camera}/image_rect_compressed"].msgtype == \
            "sensor_msgs/msg/CompressedImage"
        assert topics[f"/{camera}/camera_info"].msgtype == "sensor_msgs/msg/CameraInfo"
    assert topics["/odom"].msgtype == "nav_msgs/msg/Odometry"
    assert topics["/diagnostics"].msgtype == "diagnostic_msgs/msg/DiagnosticArray"
    groups = keyframe_groups(layout_world.records)
    keyframe_ns = [g["LIDAR_TOP"].timestamp_us * 1000 for g in groups]

    tf = list(messages(bag, ["/tf"]))
    assert [log for _, log, _ in tf] == keyframe_ns             # TF at keyframes only
    for k, (_, log, msg) in enumerate(tf):
        stamps = {stamp_ns(t.header) for t in msg.transforms}
        assert stamps == set(keyframe_ns[k:k + 2])              # this sample and the next
        edges = {(t.header.frame_id, t.child_frame_id) for t in msg.transforms}
        assert edges == {("map", "base_link")} | {("base_link", c)
                                                 for c in (*CAMERA_NAMES, "LIDAR_TOP")}

    key_images = {r.timestamp_us * 1000 for g in groups for c, r in g.items() if c != "LIDAR_TOP"}
    for camera in CAMERA_NAMES:
        for topic, log, msg in messages(bag, [f"/{camera}/image_rect_compressed",
                                              f"/{camera}/camera_info"]):
            assert msg.header.frame_id == camera
            stamp = stamp_ns(msg.header)
            if stamp in key_images:                  # logged at the sample's LiDAR time
                assert log in keyframe_ns and log != stamp
            else:
                assert log == stamp
            assert stamp >= min(key_images)          # nothing before the first keyframe
            if topic.endswith("camera_info"):
                assert list(msg.r) == [1, 0, 0, 1, 0, 0, 1, 0, 0] and len(msg.d) == 0
                assert msg.distortion_model == ""
            else:
                assert msg.format == "jpeg"

    odom = list(messages(bag, ["/odom"]))
    stamps = np.array([stamp_ns(m.header) for _, _, m in odom])
    assert np.all(np.diff(stamps) == 20_000_000)                # 50 Hz CAN pose
    delays = np.array([log for _, log, _ in odom]) - stamps
    assert {log for _, log, _ in odom} <= set(keyframe_ns)      # in bursts at keyframes
    assert delays.min() > 0 and delays.max() > 0.5e9            # up to a keyframe gap late
    assert odom[0][2].header.frame_id == "map" and odom[0][2].child_frame_id == "base_link"


def test_chris7462_layout(layout_world):
    bag = layout_world.bags["chris7462"]
    topics = bag_topics(bag)
    assert not any("tf" in t for t in topics)                   # no TF at all
    records = {r.timestamp_us * 1000: r for r in layout_world.records}
    for camera in CAMERA_NAMES:
        name = camera.lower()
        image_topic, info_topic = f"/nuscenes/{name}/image_raw", f"/nuscenes/{name}/camera_info"
        assert topics[image_topic].qos.reliable is False and topics[info_topic].qos.reliable
        for topic, log, msg in messages(bag, [image_topic, info_topic]):
            assert log == stamp_ns(msg.header) and msg.header.frame_id == f"{name}_link"
            if topic == image_topic:
                assert msg.encoding == "bgr8" and msg.step == 3 * msg.width
                want = cv2.imread(str(records[log].path), cv2.IMREAD_COLOR)
                assert msg.data.tobytes() == want.tobytes()
            else:
                assert list(msg.r) == [1, 0, 0, 0, 1, 0, 0, 0, 1] and len(msg.d) == 0
                np.testing.assert_array_equal(msg.k.reshape(3, 3), records[log].intrinsics)
    odom = list(messages(bag, ["/nuscenes/odom"]))
    assert [log for _, log, _ in odom] == sorted(records)       # one per sample_data
    for _, log, msg in odom:
        assert stamp_ns(msg.header) == log
        p = msg.pose.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], records[log].T_global_from_ego[:3, 3])


def test_nuscenes2bag_layout_converted_from_ros1(layout_world):
    bag = layout_world.bags["nuscenes2bag"]
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "sqlite3"              # rosbags-convert's default
    from rosbags.rosbag1 import Reader
    with Reader(bag.parent / f"{bag.name}.bag") as ros1:
        assert {c.topic: c.msgtype for c in ros1.connections}["/tf"] == "tf/msg/tfMessage"
    topics = bag_topics(bag)
    assert topics["/tf"].msgtype == "tf2_msgs/msg/TFMessage"    # renamed by the converter
    assert "/tf_static" not in topics and not any("camera_info" in t for t in topics)
    for camera in CAMERA_NAMES:
        name = camera.lower()
        assert topics[f"{name}/raw"].msgtype == "sensor_msgs/msg/Image"   # no leading slash
        _, log, msg = next(messages(bag, [f"{name}/raw"]))
        assert msg.header.frame_id == name and msg.encoding == "bgr8"
        assert log == stamp_ns(msg.header)
    records = sorted({r.timestamp_us * 1000 for r in layout_world.records})
    tf = list(messages(bag, ["/tf"]))
    assert [log for _, log, _ in tf] == records                 # one per ego pose
    edges = {(t.header.frame_id, t.child_frame_id) for t in tf[0][2].transforms}
    assert edges == {("odom", "base_link"), ("map", "odom")} | {
        ("base_link", c.lower()) for c in (*CAMERA_NAMES, "LIDAR_TOP")}
    _, _, odom = next(messages(bag, ["/odom"]))
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")


@pytest.mark.parametrize("layout", ["foxglove", "chris7462", "nuscenes2bag"])
def test_rig_command_names_cameras_and_frames_as_the_layout(layout, layout_world, tmp_path):
    out = tmp_path / "rig.yaml"
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "bag", "rig",
                             "--dataroot", str(layout_world.root / "world"), "--scene",
                             "scene-0001", "--layout", layout, "--out", str(out)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    rig = load_rig(out)
    converter = CONVERTERS[layout]
    assert list(rig.cameras) == converter.camera_names()
    params = yaml.safe_load(resource_path(f"config/bags/{layout}.yaml").read_text())
    pattern = params["/**"]["ros__parameters"].get("image_topic",
                                                   "/{camera}/image_rect_compressed")
    assert params["/**"]["ros__parameters"].get("camera_names",
                                                CONVERTERS["odg"].camera_names()) == list(rig.cameras)
    shipped = load_rig(resource_path("config/rig_nuscenes.yaml"))     # the world's car
    image_hw = cv2.imread(str(next(r.path for r in layout_world.records
                                   if r.channel == "CAM_FRONT"))).shape[:2]
    recorded = {t.lstrip("/") for t in bag_topics(layout_world.bags[layout])}
    for camera, channel in zip(rig.cameras, CAMERA_NAMES):
        topic = pattern.format(camera=camera)
        assert topic.lstrip("/") in recorded
        _, _, msg = next(messages(layout_world.bags[layout],
                                  [t for t in bag_topics(layout_world.bags[layout])
                                   if t.lstrip("/") == topic.lstrip("/")]))
        assert rig.cameras[camera].frame_id == msg.header.frame_id
        np.testing.assert_allclose(rig.cameras[camera].sensor2ego,
                                   shipped.cameras[channel].sensor2ego, atol=1e-9)
        assert rig.cameras[camera].image_hw == image_hw
    again = subprocess.run([sys.executable, "-m", "odg_ros.commands", "bag", "rig",
                            "--dataroot", str(layout_world.root / "world"), "--scene",
                            "scene-0001", "--out", str(out)],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "already exists" in again.stderr


def test_params_files_set_known_parameters_only():
    schema = load_schema()
    files = sorted(resource_path("config/bags").glob("*.yaml"))
    assert {f.stem for f in files} == {"foxglove", "foxglove_tf", "chris7462", "nuscenes2bag"}
    docs = (ROOT / "docs" / "bags.md").read_text()
    for path in files:
        params = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
        unknown = set(params) - set(schema) - PENDING - {"use_sim_time"}
        assert not unknown, (path.name, unknown)
        assert params["use_sim_time"] is True
        assert f"config/bags/{path.name}" in docs, path.name
