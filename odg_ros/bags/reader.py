"""Read rosbag2 bags (any storage rosbags reads; no rclpy): their topics with the recorded
QoS, and ``iter_bag``, which yields ``(topic, stamp_ns, msgtype, cdr_bytes)`` in log-time order.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from odg_ros.bags import layout


@dataclass(frozen=True)
class BagTopic:
    name: str
    msgtype: str
    count: int
    qos: layout.TopicQos | None  # the offered QoS recorded in the bag, None when absent


def bag_topics(path) -> dict[str, BagTopic]:
    """Topics of a rosbag2 bag (any storage rosbags reads) with their recorded QoS."""
    from rosbags.interfaces import QosDurability, QosReliability
    from rosbags.rosbag2 import Reader

    with Reader(Path(path)) as reader:
        result = {}
        for conn in reader.connections:
            profiles = getattr(conn.ext, "offered_qos_profiles", None) or []
            qos = None
            if profiles:
                p = profiles[0]
                qos = layout.TopicQos(
                    reliable=p.reliability != QosReliability.BEST_EFFORT,
                    transient_local=p.durability == QosDurability.TRANSIENT_LOCAL,
                    depth=max(1, int(p.depth or 1)))
            previous = result.get(conn.topic)
            count = conn.msgcount + (previous.count if previous else 0)
            result[conn.topic] = BagTopic(conn.topic, conn.msgtype, count, qos)
        return result


def iter_bag(path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, str, bytes]]:
    """Yield ``(topic, log_time_ns, msgtype, cdr_bytes)`` of a bag in log-time order."""
    from rosbags.rosbag2 import Reader

    wanted = None if topics is None else set(topics)
    with Reader(Path(path)) as reader:
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not connections:
            return
        for conn, timestamp, raw in reader.messages(connections=connections):
            yield conn.topic, int(timestamp), conn.msgtype, bytes(raw)
