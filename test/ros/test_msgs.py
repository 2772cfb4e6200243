"""odg_ros_msgs: CDR round trips and a publisher in another process, on loopback-only DDS."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time

import numpy as np

from testing.ros import RawRecorder, non_loopback, udp_local_addresses
from testing.ros import object_array, voxel_grid
from testing import REPOSITORY


def test_round_trips(rclpy_module):
    from rclpy.serialization import deserialize_message, serialize_message

    import odg_ros_msgs.msg as m

    grid, labels = voxel_grid(m)
    back = deserialize_message(serialize_message(grid), m.SemanticVoxelGrid)
    assert back == grid
    restored = np.frombuffer(bytes(back.labels), np.uint8).reshape(back.size_x, back.size_y,
                                                                   back.size_z)
    np.testing.assert_array_equal(restored, labels)
    # The documented xyz_c flat index.
    x, y, z = 123, 45, 6
    assert bytes(back.labels)[(x * back.size_y + y) * back.size_z + z] == labels[x, y, z]
    assert len(back.observed) == 0 and back.memory_order == "xyz_c"

    array = object_array(m)
    back = deserialize_message(serialize_message(array), m.DynamicObjectArray)
    assert back == array and back.objects[2].class_name == "bus"
    single = array.objects[1]
    assert deserialize_message(serialize_message(single), m.DynamicObject) == single

    empty = m.DynamicObjectArray()
    assert deserialize_message(serialize_message(empty), m.DynamicObjectArray) == empty


def test_tf2_msgs_has_the_upstream_type_hash(ros_context, rclpy_module):
    """The venv's TFMessage (built from tools/ros_shims when PyPI has no tf2_msgs) carries the
    upstream type hash, so it talks to real ROS 2 nodes. The hash is read back from the graph."""
    from tf2_msgs.msg import TFMessage

    upstream = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    node = rclpy_module.create_node("tf_hash_check", context=ros_context)
    node.create_publisher(TFMessage, "/tf_hash_check", 1)
    (info,) = node.get_publishers_info_by_topic("/tf_hash_check")
    assert info.topic_type == "tf2_msgs/msg/TFMessage"
    assert str(info.topic_type_hash) == upstream
    node.destroy_node()


PUBLISHER_SCRIPT = textwrap.dedent("""
    import os, sys, time
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    import odg_ros_msgs.msg as m
    from testing.ros import voxel_grid, object_array
    rclpy.init()
    node = rclpy.create_node("msgs_test_publisher")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    grid_pub = node.create_publisher(m.SemanticVoxelGrid, "/test/occupancy", qos)
    obj_pub = node.create_publisher(m.DynamicObjectArray, "/test/objects", qos)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and (grid_pub.get_subscription_count() == 0
                                           or obj_pub.get_subscription_count() == 0):
        time.sleep(0.02)
    for i in range(3):
        grid_pub.publish(voxel_grid(m, seed=i)[0])
        obj_pub.publish(object_array(m))
    grid_pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10))
    obj_pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10))
    from testing.ros import udp_local_addresses
    print("SOCKETS", sorted(udp_local_addresses(os.getpid())))
    node.destroy_node()
    rclpy.shutdown()
""")


def test_publish_in_another_process(ros_context, rclpy_module):
    """A 1.9 MB SemanticVoxelGrid and an object array cross processes (shared memory), and
    neither process has a UDP socket outside 127.0.0.0/8."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message

    import odg_ros_msgs.msg as m

    node = rclpy_module.create_node("msgs_test_subscriber", context=ros_context)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    recorder = RawRecorder(node, {"/test/occupancy": (m.SemanticVoxelGrid, qos),
                                  "/test/objects": (m.DynamicObjectArray, qos)})
    # from the repository root: `-c` puts it on the path, so testing/ imports
    child = subprocess.Popen([sys.executable, "-c", PUBLISHER_SCRIPT], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, cwd=REPOSITORY)
    executor = rclpy_module.executors.SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and sum(recorder.counts().values()) < 6:
        executor.spin_once(timeout_sec=0.05)
    own_sockets = udp_local_addresses(os.getpid())
    out, err = child.communicate(timeout=30)
    executor.shutdown()
    node.destroy_node()
    assert child.returncode == 0, err
    assert recorder.counts() == {"/test/occupancy": 3, "/test/objects": 3}
    for i, (_, raw) in enumerate(recorder.received["/test/occupancy"]):
        grid = deserialize_message(raw, m.SemanticVoxelGrid)
        assert grid == voxel_grid(m, seed=i)[0]
    assert deserialize_message(recorder.received["/test/objects"][0][1],
                               m.DynamicObjectArray) == object_array(m)
    child_sockets = eval(out.split("SOCKETS", 1)[1].strip())
    assert own_sockets and child_sockets
    assert not non_loopback(own_sockets), own_sockets
    assert not non_loopback(set(child_sockets)), child_sockets
