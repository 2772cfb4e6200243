"""Publish a rosbag2 bag with rclpy, for machines without rosbag2 (``odg replay``).

Messages go out as the raw CDR bytes stored in the bag (``Publisher.publish`` accepts
serialized bytes), with the message types named in the bag, so nothing is deserialized.
Inter-message timing follows the bag's log times divided by ``rate``. QoS per topic is that of
``odg_ros.bags.layout.topic_qos``: ``/tf_static`` reliable + transient local (late joiners
still get the sensor frames), camera images, camera infos and point clouds best effort (sensor
data), the rest reliable. With ``clock``, ``/clock`` carries the bag time of every message just before it.
"""
from __future__ import annotations

import importlib
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from odg_ros.bags import layout
from odg_ros.bags.reader import bag_topics, iter_bag


def message_class(msgtype: str):
    """'sensor_msgs/msg/CompressedImage' -> the rclpy message class (clear error if missing)."""
    package, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError) as error:
        raise LookupError(f"message type {msgtype} is not available to rclpy ({error})") from error


def rclpy_qos(qos: layout.TopicQos):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=qos.depth,
        reliability=ReliabilityPolicy.RELIABLE if qos.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if qos.transient_local
                    else DurabilityPolicy.VOLATILE))


@dataclass
class ReplayStats:
    published: Counter = field(default_factory=Counter)
    skipped_topics: dict[str, str] = field(default_factory=dict)  # topic -> why
    loops: int = 0
    interrupted: bool = False
    wall_s: float = 0.0

    def __str__(self) -> str:
        total = sum(self.published.values())
        text = f"published {total} messages on {len(self.published)} topics in {self.wall_s:.1f} s"
        if self.loops > 1:
            text += f" ({self.loops} loops)"
        for topic, why in self.skipped_topics.items():
            text += f"\n  skipped {topic}: {why}"
        return text + (" -- interrupted" if self.interrupted else "")


class _Interrupted(Exception):
    pass


def _raise_interrupted(signum, frame):
    raise _Interrupted()


def replay(bag, *, rate: float = 1.0, clock: bool = False, loop: bool = False,
           wait_for_subscribers_s: float = 0.0, progress: bool = True,
           node_name: str = "odg_replay") -> ReplayStats:
    """Publish every message of ``bag`` in log-time order; returns what was published.

    wait_for_subscribers_s: before the first message, wait up to this long until every topic
    has at least one subscriber (nothing published to an unmatched volatile topic is kept).
    Ctrl-C or SIGTERM stop it cleanly (stats.interrupted). rclpy must not be initialised in
    the default context by the caller; the DDS environment is the caller's business
    (``odg replay`` applies odg_ros.ros.dds.use_localhost_dds first).
    """
    import rclpy
    from rclpy.duration import Duration
    from rclpy.signals import SignalHandlerOptions

    if not (rate > 0 and rate < float("inf")):
        raise ValueError(f"rate must be a positive number, got {rate}")
    bag = Path(bag)
    with _readable(bag, "cannot open it"):
        topics = bag_topics(bag)
    if not topics:
        raise ValueError(f"{bag}: the bag has no topics")
    stats = ReplayStats()

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    # Our own SIGINT/SIGTERM handling: rclpy's would shut the context down under our feet.
    # (Signal handlers can only be set from the main thread; elsewhere the caller stops us.)
    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, _raise_interrupted)
                    for sig in (signal.SIGINT, signal.SIGTERM)}
    node = None
    start = time.monotonic()
    try:
        node = rclpy.create_node(node_name, context=context)
        publishers = _create_publishers(node, bag, topics, stats)
        clock_pub = None
        if clock:
            from rosgraph_msgs.msg import Clock
            clock_pub = node.create_publisher(Clock, layout.CLOCK_TOPIC, 10)
        if wait_for_subscribers_s > 0:
            _wait_for_subscribers(node, publishers, wait_for_subscribers_s)
        total = sum(topics[t].count for t in publishers)
        while True:
            stats.loops += 1
            _publish_once(bag, publishers, clock_pub, rate, stats,
                          tqdm(total=total, desc=f"replay {bag.name}", unit="msg",
                               disable=not progress))
            if not loop:
                break
        # Reliable messages still in flight would be lost with the participant.
        for name, pub in publishers.items():
            if layout.topic_qos(name, topics[name].msgtype).reliable:
                pub.wait_for_all_acked(Duration(seconds=2))
    except (_Interrupted, KeyboardInterrupt):
        stats.interrupted = True
    finally:
        stats.wall_s = time.monotonic() - start
        # A second Ctrl-C during clean-up must not leave the participant half destroyed.
        for sig in previous:
            signal.signal(sig, signal.SIG_IGN)
        if node is not None:
            node.destroy_node()
        context.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return stats


def _create_publishers(node, bag: Path, topics: dict, stats: ReplayStats) -> dict:
    """topic -> publisher with the bag's QoS, for every topic whose type rclpy knows."""
    publishers = {}
    for name, info in topics.items():
        try:
            cls = message_class(info.msgtype)
        except LookupError as error:
            stats.skipped_topics[name] = str(error)
            continue
        qos = layout.topic_qos(name, info.msgtype)
        if qos.transient_local:  # late joiners get every latched message of the bag
            qos = layout.TopicQos(True, True, depth=max(1, min(info.count, 100)))
        publishers[name] = node.create_publisher(cls, name, rclpy_qos(qos))
    if not publishers:
        raise ValueError(f"{bag}: no topic has a message type rclpy knows")
    return publishers


def _wait_for_subscribers(node, publishers: dict, seconds: float) -> None:
    """Up to ``seconds`` until every topic has a subscriber; a warning names those without."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(
            p.get_subscription_count() == 0 for p in publishers.values()):
        time.sleep(0.02)
    lonely = [t for t, p in publishers.items() if p.get_subscription_count() == 0]
    if lonely:
        node.get_logger().warning(
            f"no subscriber after {seconds:.1f} s on: {', '.join(lonely)}")


def _publish_once(bag: Path, publishers: dict, clock_pub, rate: float, stats: ReplayStats,
                  bar) -> None:
    """One pass over the bag, each message at its log time scaled by ``rate`` (and /clock
    before each new stamp when ``clock_pub``)."""
    wall0 = bag0 = None
    last_clock_ns = None
    try:
        for topic, stamp_ns, _, raw in _messages(bag, publishers, stats):
            if bag0 is None:
                wall0, bag0 = time.monotonic(), stamp_ns
            delay = wall0 + (stamp_ns - bag0) * 1e-9 / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if clock_pub is not None and stamp_ns != last_clock_ns:
                clock_pub.publish(_clock_message(stamp_ns))
                last_clock_ns = stamp_ns
            publishers[topic].publish(raw)
            stats.published[topic] += 1
            bar.update(1)
    finally:
        bar.close()


class _readable:
    """Turns what reading a damaged, truncated or foreign bag raises into one ValueError
    line (``odg replay`` shows it as its error, exit code 2)."""

    def __init__(self, bag: Path, doing: str):
        self.bag, self.doing = bag, doing

    def __enter__(self):
        return self

    def __exit__(self, kind, error, traceback):
        # whatever the reader raises on bytes it cannot parse (its own ReaderError, but also
        # struct.error, OverflowError, KeyError... from a corrupt chunk): only reading is
        # inside this block
        if kind is not None and issubclass(kind, Exception) and \
                not issubclass(kind, _Interrupted):             # Ctrl-C while reading
            raise ValueError(f"{self.bag} is not a readable rosbag2 bag ({self.doing}: "
                             f"{type(error).__name__}: {error})") from error
        return False


def _messages(bag: Path, topics, stats: ReplayStats):
    """iter_bag, a reading error named with the messages published before it."""
    messages = iter_bag(bag, topics=topics)
    while True:
        with _readable(bag, f"after {sum(stats.published.values())} messages"):
            item = next(messages, None)
        if item is None:
            return
        yield item


def _clock_message(stamp_ns: int):
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock
    return Clock(clock=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000))
