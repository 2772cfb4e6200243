"""Helpers for the ROS tests: which UDP addresses a process has bound, a raw subscriber that
records everything it receives, and filled SemanticVoxelGrid / DynamicObjectArray messages."""
from __future__ import annotations

import os
import socket
import struct
import time
from collections import defaultdict

import numpy as np



def udp_local_addresses(pid: int) -> set[str]:
    """'ip:port' of every UDP (v4 and v6) socket the process holds, read from /proc."""
    inodes = set()
    fd_dir = f"/proc/{pid}/fd"
    for fd in os.listdir(fd_dir):
        try:
            target = os.readlink(os.path.join(fd_dir, fd))
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    addresses = set()
    for table, family in (("udp", socket.AF_INET), ("udp6", socket.AF_INET6)):
        try:
            lines = open(f"/proc/{pid}/net/{table}").read().splitlines()[1:]
        except FileNotFoundError:
            continue
        for line in lines:
            fields = line.split()
            if fields[9] not in inodes:
                continue
            hex_ip, hex_port = fields[1].split(":")
            raw = bytes.fromhex(hex_ip)
            if family == socket.AF_INET:
                ip = socket.inet_ntop(family, struct.pack("<I", int(hex_ip, 16)))
            else:  # four little-endian 32-bit words
                ip = socket.inet_ntop(family, b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))
            addresses.add(f"{ip}:{int(hex_port, 16)}")
    return addresses


def non_loopback(addresses: set[str]) -> set[str]:
    return {a for a in addresses if not (a.startswith("127.") or a.startswith("::1:"))}


class RawRecorder:
    """Subscribes to topics and keeps (receive time, raw CDR bytes) per topic."""

    def __init__(self, node, topics: dict[str, tuple[type, object]]):
        self.received = defaultdict(list)
        self.subscriptions = [
            node.create_subscription(cls, topic, self._callback(topic), qos, raw=True)
            for topic, (cls, qos) in topics.items()]

    def _callback(self, topic):
        def store(raw):
            self.received[topic].append((time.monotonic(), bytes(raw)))
        return store

    def counts(self) -> dict[str, int]:
        return {topic: len(items) for topic, items in self.received.items()}


def voxel_grid(msgs_module, size=(200, 200, 16), seed=0):
    from geometry_msgs.msg import Point, Pose, Quaternion
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 18, size=size, dtype=np.uint8)
    msg = msgs_module.SemanticVoxelGrid()
    msg.header.frame_id = "base_link"
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_533_151_603, 547_590_000
    msg.origin = Pose(position=Point(x=-40.0, y=-40.0, z=-1.0), orientation=Quaternion(w=1.0))
    msg.resolution = float(np.float32(0.4))  # exactly representable as float32 on the wire
    msg.size_x, msg.size_y, msg.size_z = size
    msg.memory_order = msg.MEMORY_ORDER_XYZ_C
    msg.free_label, msg.unknown_label = 17, 255
    msg.labels = labels.tobytes()
    msg.confidence = rng.integers(0, 256, size=labels.size, dtype=np.uint8).tobytes()
    msg.observed = b""
    msg.class_names = [f"class_{i}" for i in range(18)]
    return msg, labels


def object_array(msgs_module):
    from geometry_msgs.msg import Twist, Vector3
    array = msgs_module.DynamicObjectArray()
    array.header.frame_id = "base_link"
    for i in range(3):
        obj = msgs_module.DynamicObject(class_id=i, class_name=["car", "truck", "bus"][i],
                                        score=float(np.float32(0.5 + 0.1 * i)), id=100 + i)
        obj.pose.position.x, obj.pose.orientation.z, obj.pose.orientation.w = 3.0 * i, 0.6, 0.8
        obj.size = Vector3(x=4.5, y=1.9, z=1.6)
        obj.velocity = Twist(linear=Vector3(x=1.0 * i, y=-0.5))
        array.objects.append(obj)
    return array
