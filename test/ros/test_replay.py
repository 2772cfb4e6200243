"""odg replay: a bag published by a separate process arrives complete, byte-exact and on time."""
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
def bag(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_nuscenes")
    tiny_nuscenes.build(root, scene_durations_s=(1.0,))
    out = tmp_path_factory.mktemp("bags") / "scene-0001"
    write_scene_bag(NuScenesSensorTables(root).scene_records("scene-0001"), out, progress=False)
    return out


def start_replay(bag, *args):
    return subprocess.Popen([sys.executable, "-m", "odg_ros.commands", "replay", str(bag), "--quiet",
                             *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


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


def test_bad_arguments(rclpy_module, tmp_path, bag):
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay", str(tmp_path)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "not a rosbag2 folder" in result.stderr
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "replay", str(bag),
                             "--rate", "0"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--rate: must be > 0" in result.stderr
