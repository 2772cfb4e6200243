"""odg replay: a bag published by a separate process arrives complete, byte-exact and on time;
several bags play back to back (the bag time jumps), --topics and --remap as ros2 bag play
has them."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from testing import tiny_nuscenes
from odg_ros.bags import layout
from odg_ros.bags.reader import bag_topics, iter_bag
from odg_ros.bags.writer import write_scene_bag
from odg_ros.bags.nuscenes_source import NuScenesSensorTables
from testing.ros import RawRecorder, non_loopback, udp_local_addresses


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """A folder of two bags: scene-0001 (1 s) and scene-0002 (0.5 s, 60 s later)."""
    root = tmp_path_factory.mktemp("tiny_nuscenes")
    tiny_nuscenes.build(root, scene_durations_s=(1.0, 0.5))
    folder = tmp_path_factory.mktemp("bags")
    tables = NuScenesSensorTables(root)
    for scene in ("scene-0001", "scene-0002"):
        write_scene_bag(tables.scene_records(scene), folder / scene, progress=False)
    return folder


@pytest.fixture(scope="module")
def bag(bags):
    return bags / "scene-0001"


def start_replay(*bags_then_options):
    return subprocess.Popen([sys.executable, "-m", "odg_ros.commands", "replay",
                             *map(str, bags_then_options), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def subscribe_all(rclpy_module, context, bag, extra=None):
    """A node with one raw subscription per bag topic, QoS compatible with the replay's."""
    from odg_ros.ros.replay import message_class, rclpy_qos

    node = rclpy_module.create_node("replay_test_subscriber", context=context)
    topics = {}
    for name, info in bag_topics(bag).items():
        offered = layout.topic_qos(name, info.msgtype)
        # Reliable where the publisher is reliable, best effort where it is; deep queues so
        # that nothing is dropped on our side.
        wanted = layout.TopicQos(offered.reliable, offered.transient_local, depth=1000)
        topics[name] = (message_class(info.msgtype), rclpy_qos(wanted))
    topics.update(extra or {})
    recorder = RawRecorder(node, topics)
    executor = rclpy_module.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return node, executor, recorder


def same_cdr(received: bytes, sent: bytes) -> bool:
    """Equal CDR payloads: DDS pads a serialized payload with zeros to a multiple of 4 bytes."""
    pad = received[len(sent):]
    return received[:len(sent)] == sent and len(pad) == (-len(sent)) % 4 and not any(pad)


def spin_until_exit(executor, process, timeout=60.0):
    deadline = time.monotonic() + timeout
    while process.poll() is None and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    end = time.monotonic() + 0.5  # what is still queued locally
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.01)
    out, err = process.communicate(timeout=10)
    return out, err


def test_every_message_arrives_byte_exact_and_on_time(ros_context, rclpy_module, bag):
    rate = 2.0
    node, executor, recorder = subscribe_all(rclpy_module, ros_context, bag)
    replay = start_replay(bag, "--rate", str(rate), "--wait-for-subscribers", "20")
    replay_sockets = set()
    deadline = time.monotonic() + 60
    while replay.poll() is None and not recorder.received and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    if replay.poll() is None:
        replay_sockets = udp_local_addresses(replay.pid)
    own_sockets = udp_local_addresses(os.getpid())
    out, err = spin_until_exit(executor, replay)
    node.destroy_node()
    assert replay.returncode == 0, err
    assert "published 376 messages" in out

    expected = {}
    for topic, _, _, raw in iter_bag(bag):
        expected.setdefault(topic, []).append(raw)
    # Every topic, camera topics (best effort) included: SHM on one machine at this modest
    # rate does not drop, so any loss here is a real fault.
    assert recorder.counts() == {t: len(v) for t, v in expected.items()}
    for topic, raws in expected.items():
        for (_, got), want in zip(recorder.received[topic], raws):
            assert same_cdr(got, want), topic

    # Timing: /tf arrivals span the bag's duration / rate (never faster; slack for a busy CI).
    arrivals = [t for t, _ in recorder.received["/tf"]]
    bag_stamps = [s for _, s, _, _ in iter_bag(bag, topics=["/tf"])]
    want = (bag_stamps[-1] - bag_stamps[0]) * 1e-9 / rate
    assert want * 0.9 <= arrivals[-1] - arrivals[0] <= want + 1.0

    assert replay_sockets and not non_loopback(replay_sockets), replay_sockets
    assert not non_loopback(own_sockets), own_sockets


def test_clock_and_late_tf_static(ros_context, rclpy_module, bag):
    """/clock carries the bag time; a subscriber that joins after /tf_static was published
    still gets it (transient local)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from rosgraph_msgs.msg import Clock
    from tf2_msgs.msg import TFMessage

    node, executor, recorder = subscribe_all(
        rclpy_module, ros_context, bag,
        extra={"/clock": (Clock, QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))})
    replay = start_replay(bag, "--rate", "4", "--clock", "--wait-for-subscribers", "20")
    # Join /tf_static late: after the replay has published its first messages.
    while replay.poll() is None and len(recorder.received["/tf"]) < 5:
        executor.spin_once(timeout_sec=0.01)
    late = {}
    node.create_subscription(
        TFMessage, "/tf_static", lambda raw: late.setdefault("raw", raw),
        QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL), raw=True)
    out, err = spin_until_exit(executor, replay)
    assert replay.returncode == 0, err
    assert "raw" in late, "late /tf_static subscriber got nothing"
    frames = {tf.child_frame_id for tf in deserialize_message(late["raw"], TFMessage).transforms}
    assert frames == set(layout.CAMERA_NAMES) | {"LIDAR_TOP"}

    clock = [deserialize_message(raw, Clock).clock for _, raw in recorder.received["/clock"]]
    clock_ns = [c.sec * 1_000_000_000 + c.nanosec for c in clock]
    bag_ns = sorted({s for _, s, _, _ in iter_bag(bag)})
    assert clock_ns == bag_ns  # one tick per distinct bag time, in order
    node.destroy_node()


def test_ctrl_c_stops_cleanly(rclpy_module, bag):
    replay = start_replay(bag, "--loop", "--rate", "1")
    time.sleep(3.0)  # start-up (imports, participant) and some publishing
    assert replay.poll() is None, replay.communicate()
    replay.send_signal(signal.SIGINT)
    out, err = replay.communicate(timeout=20)
    assert replay.returncode == 130, (out, err)
    assert "interrupted" in out and "Traceback" not in err


def test_bags_back_to_back_with_topics_and_remap(ros_context, rclpy_module, bags):
    """Two bags in the order given (the later scene first: the bag time jumps back 60 s),
    only two of their topics, /tf published as /replayed/tf."""
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import CompressedImage
    from tf2_msgs.msg import TFMessage

    reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    best_effort = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
    node = rclpy_module.create_node("replay_test_remap", context=ros_context)
    recorder = RawRecorder(node, {"/replayed/tf": (TFMessage, reliable),
                                  "/tf": (TFMessage, reliable),
                                  "/odom": (Odometry, reliable),
                                  "/CAM_FRONT/image_rect_compressed": (CompressedImage,
                                                                       best_effort),
                                  "/clock": (Clock, reliable)})
    executor = rclpy_module.executors.SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    order = [bags / "scene-0002", bags / "scene-0001"]
    replay = start_replay(order[0], order[1], "--rate", "4", "--clock",
                          "--topics", "/tf", "/CAM_FRONT/image_rect_compressed",
                          "--remap", "/tf:=/replayed/tf", "--wait-for-subscribers", "20")
    out, err = spin_until_exit(executor, replay)
    node.destroy_node()
    assert replay.returncode == 0, err
    sent = sum(1 for bag in order for _ in iter_bag(bag, topics=[
        "/tf", "/CAM_FRONT/image_rect_compressed"]))
    assert out.startswith(f"published {sent} messages on 2 topics"), out
    assert "from 2 bags" in out and "remapped /tf -> /replayed/tf" in out, out
    playing = [line for line in err.splitlines() if " playing " in line]
    assert [line.split(": ", 2)[1] for line in playing] == ["playing 1/2", "playing 2/2"], err
    assert str(order[0]) in playing[0] and str(order[1]) in playing[1]

    for topic, published_as in (("/tf", "/replayed/tf"),
                                ("/CAM_FRONT/image_rect_compressed",) * 2):
        want = [raw for bag in order for _, _, _, raw in iter_bag(bag, topics=[topic])]
        got = [raw for _, raw in recorder.received[published_as]]
        assert len(got) == len(want) and all(map(same_cdr, got, want)), topic
    assert not recorder.received["/tf"]              # remapped away, nothing under the old name
    assert not recorder.received["/odom"]            # not among --topics
    clock = [deserialize_message(raw, Clock).clock for _, raw in recorder.received["/clock"]]
    clock_ns = [c.sec * 1_000_000_000 + c.nanosec for c in clock]
    want_ns = [sorted({s for _, s, _, _ in iter_bag(bag, topics=["/tf", "/CAM_FRONT/"
                                                                 "image_rect_compressed"])})
               for bag in order]
    assert clock_ns == want_ns[0] + want_ns[1]       # one jump back, at the second bag
    assert want_ns[1][0] < want_ns[0][-1] - 50e9


def test_bad_arguments(rclpy_module, tmp_path, bag):
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay", str(tmp_path)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "is not a rosbag2 bag" in result.stderr
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay",
                             str(tmp_path / "missing")], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2 and f"{tmp_path / 'missing'} not found" in result.stderr
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay", str(bag),
                             "--topics", "/tf", "/nope"], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2 and "--topics: not in the bag: /nope" in result.stderr
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay", str(bag),
                             "--remap", "/tf"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "expected old_topic:=new_topic" in result.stderr
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay", str(bag),
                             "--rate", "0"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--rate: must be > 0" in result.stderr
