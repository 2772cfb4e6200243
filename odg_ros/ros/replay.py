"""Publish rosbag2 bags with rclpy, for machines without rosbag2 (``odg replay``).

Messages go out as the raw CDR bytes stored in the bag (``Publisher.publish`` accepts
serialized bytes), with the message types named in the bag, so nothing is deserialized.
Inter-message timing follows the bag's log times divided by ``rate``. QoS per topic is that of
``odg_ros.bags.layout.topic_qos``: ``/tf_static`` reliable + transient local (late joiners
still get the sensor frames), camera images, camera infos and point clouds best effort (sensor
data), the rest reliable. With ``clock``, ``/clock`` carries the bag time of every message
just before it.

Several bags play back to back, each from its first message right after the previous one's
last: the bag time (and ``/clock``) jumps to the next bag's start, as when a bag restarts.
As ``ros2 bag play`` has them: ``topics`` publishes only those topics (names as recorded in
the bags), and ``remap`` rules ``old:=new`` rename topics the ROS way (the rules are the
replay node's ``--ros-args --remap`` rules, as rosbag2's player applies them). A recording
that ended badly (odg_ros.bags.reader) plays up to its damage after one warning.
"""
from __future__ import annotations

import importlib
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from ..bags import layout
from ..bags.reader import Bag, find_bags, open_bag


def message_class(msgtype: str):
    """'sensor_msgs/msg/CompressedImage' -> the rclpy message class (clear error if missing)."""
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise LookupError(f"{msgtype!r} is not a ROS 2 message type (package/msg/Name)")
    package, kind, name = parts
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
    published: Counter = field(default_factory=Counter)      # bag topic -> messages
    skipped_topics: dict[str, str] = field(default_factory=dict)  # topic -> why
    remapped: dict[str, str] = field(default_factory=dict)   # bag topic -> published as
    bags: list[tuple[str, int]] = field(default_factory=list)    # (bag, messages) as played
    loops: int = 0
    interrupted: bool = False
    wall_s: float = 0.0

    def __str__(self) -> str:
        total = sum(self.published.values())
        text = f"published {total} messages on {len(self.published)} topics in {self.wall_s:.1f} s"
        names = {name for name, _ in self.bags}
        if len(names) > 1:
            text += f" from {len(names)} bags"
        if self.loops > 1:
            text += f" ({self.loops} loops)"
        for topic, new in sorted(self.remapped.items()):
            text += f"\n  remapped {topic} -> {new}"
        for topic, why in self.skipped_topics.items():
            text += f"\n  skipped {topic}: {why}"
        return text + (" -- interrupted" if self.interrupted else "")


class _Interrupted(Exception):
    pass


def _raise_interrupted(signum, frame):
    raise _Interrupted()


def _absolute(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


def check_remap_rules(rules: Sequence[str]) -> list[str]:
    """``old:=new`` rules as ``ros2 bag play --remap`` takes them; ValueError names a bad one."""
    for rule in rules:
        old, sep, new = rule.partition(":=")
        if not sep or not old.strip() or not new.strip():
            raise ValueError(f"--remap {rule!r}: expected old_topic:=new_topic")
    return list(rules)


def select_topics(bags: Sequence[Bag], topics: Sequence[str] | None) -> dict[str, str]:
    """topic -> message type of every topic to publish: those of ``topics`` (all when None),
    matched as recorded or with a leading ``/`` added to the recorded name. A topic of
    ``topics`` that no bag has is a ValueError (a misspelt name plays nothing)."""
    recorded: dict[str, str] = {}
    for bag in bags:
        for name, info in bag.topics.items():
            recorded.setdefault(name, info.msgtype)
    if topics is None:
        return recorded
    wanted = {_absolute(t) for t in topics}
    missing = sorted(wanted - {_absolute(name) for name in recorded})
    if missing:
        raise ValueError(f"--topics: not in {'any of the bags' if len(bags) > 1 else 'the bag'}: "
                         f"{', '.join(missing)} (it has: {', '.join(sorted(recorded))})")
    return {name: t for name, t in recorded.items() if _absolute(name) in wanted}


def open_bags(paths, warn: Callable[[str], None] | None = None) -> list[Bag]:
    """Every bag the paths name (folders of bags in name order), opened; one warning per
    recording that ended badly."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    bags = []
    for path in paths:
        for bag_path in find_bags(path):
            bag = open_bag(bag_path)
            if bag.message_count == 0:
                raise ValueError(bag.damage or f"{bag_path}: the bag has no messages")
            if bag.damage and warn is not None:
                warn(bag.damage)
            bags.append(bag)
    return bags


def replay(bags, *, rate: float = 1.0, clock: bool = False, loop: bool = False,
           topics: Sequence[str] | None = None, remap: Sequence[str] = (),
           wait_for_subscribers_s: float = 0.0, progress: bool = True,
           node_name: str = "odg_replay",
           say: Callable[[str], None] | None = None) -> ReplayStats:
    """Publish the messages of ``bags`` (a path or paths: bags, folders of bags), one bag
    after the other, each in log-time order; returns what was published.

    topics: only these topics (None: all); remap: ``old:=new`` rules. say: called with one
    line per bag as it starts playing and with the warning of a recording that ended badly.
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
    remap = check_remap_rules(remap)
    warn = None if say is None else (lambda text: say(f"warning: {text}"))
    opened = open_bags(bags, warn=warn)
    selected = select_topics(opened, topics)
    stats = ReplayStats()

    context = rclpy.Context()
    # args=[]: rcl must not read this process's command line (its --remap rules are ours)
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    # Our own SIGINT/SIGTERM handling: rclpy's would shut the context down under our feet.
    # (Signal handlers can only be set from the main thread; elsewhere the caller stops us.)
    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, _raise_interrupted)
                    for sig in (signal.SIGINT, signal.SIGTERM)}
    node = None
    start = time.monotonic()
    try:
        node = _create_node(rclpy, node_name, context, remap)
        publishers = _create_publishers(node, opened, selected, stats)
        clock_pub = None
        if clock:
            from rosgraph_msgs.msg import Clock
            clock_pub = node.create_publisher(Clock, layout.CLOCK_TOPIC, 10)
        if wait_for_subscribers_s > 0:
            waited = dict(publishers)
            if clock_pub is not None:     # a use_sim_time node must not miss the first ticks
                waited[layout.CLOCK_TOPIC] = clock_pub
            _wait_for_subscribers(node, waited, wait_for_subscribers_s)
        while True:
            stats.loops += 1
            _play_bags(opened, publishers, clock_pub, rate, stats, progress, say)
            if not loop:
                break
        # Reliable messages still in flight would be lost with the participant.
        for name, pub in publishers.items():
            if layout.topic_qos(name, selected[name]).reliable:
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


def _create_node(rclpy, name: str, context, remap: list[str]):
    """The replay node, with the remap rules as its ROS arguments (rcl parses them)."""
    from rclpy.exceptions import InvalidNodeNameException
    args = ["--ros-args"] + [item for rule in remap for item in ("--remap", rule)] \
        if remap else None
    try:
        return rclpy.create_node(name, context=context, cli_args=args)
    except (InvalidNodeNameException, RuntimeError) as error:
        text = " ".join(str(error).split()).split(", at ")[0]
        raise ValueError(f"--remap: {text}") from None


def _create_publishers(node, bags: list[Bag], selected: dict[str, str],
                       stats: ReplayStats) -> dict:
    """topic -> publisher with the layout's QoS, for every selected topic whose type rclpy
    knows and that has the same type in every bag."""
    publishers = {}
    for name, msgtype in selected.items():
        others = sorted({b.topics[name].msgtype for b in bags if name in b.topics} - {msgtype})
        if others:
            stats.skipped_topics[name] = (f"{msgtype} in one bag, {', '.join(others)} in "
                                          "another")
            continue
        try:
            cls = message_class(msgtype)
        except LookupError as error:
            stats.skipped_topics[name] = str(error)
            continue
        qos = layout.topic_qos(name, msgtype)
        if qos.transient_local:  # late joiners get every latched message of the bags
            count = sum(b.topics[name].count for b in bags if name in b.topics)
            qos = layout.TopicQos(True, True, depth=max(1, min(count, 100)))
        publishers[name] = node.create_publisher(cls, name, rclpy_qos(qos))
        if publishers[name].topic_name != _absolute(name):
            stats.remapped[name] = publishers[name].topic_name
    if not publishers:
        raise ValueError("no topic to publish: " + "; ".join(
            f"{t}: {why}" for t, why in stats.skipped_topics.items()))
    return publishers


def _wait_for_subscribers(node, publishers: dict, seconds: float) -> None:
    """Up to ``seconds`` until every topic has a subscriber; a warning names those without."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(
            p.get_subscription_count() == 0 for p in publishers.values()):
        time.sleep(0.02)
    lonely = [p.topic_name for p in publishers.values() if p.get_subscription_count() == 0]
    if lonely:
        node.get_logger().warning(
            f"no subscriber after {seconds:.1f} s on: {', '.join(lonely)}")


def _play_bags(bags: list[Bag], publishers: dict, clock_pub, rate: float, stats: ReplayStats,
               progress: bool, say) -> None:
    """One pass over the bags, back to back, each announced (with several, or looping)."""
    for index, bag in enumerate(bags):
        total = sum(bag.topics[t].count for t in publishers if t in bag.topics)
        if say is not None and (len(bags) > 1 or stats.loops > 1):
            say(f"playing {index + 1}/{len(bags)}: {bag.path} "
                f"({bag.duration_s:.1f} s, {total} messages)")
        count = _publish_bag(bag, publishers, clock_pub, rate, stats,
                             tqdm(total=total, desc=f"replay {bag.name}", unit="msg",
                                  disable=not progress))
        stats.bags.append((bag.name, count))


def _publish_bag(bag: Bag, publishers: dict, clock_pub, rate: float, stats: ReplayStats,
                 bar) -> int:
    """One pass over one bag, each message at its log time (from the bag's first message)
    scaled by ``rate``, and /clock before each new stamp when ``clock_pub``. Returns the
    messages published."""
    wall0 = bag0 = None
    last_clock_ns = None
    count = 0
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
            count += 1
            bar.update(1)
    finally:
        bar.close()
    return count


class _readable:
    """Turns what reading a damaged or foreign bag raises into one ValueError line
    (``odg replay`` shows it as its error, exit code 2)."""

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


def _messages(bag: Bag, topics, stats: ReplayStats):
    """The bag's messages on ``topics``, a reading error named with the messages published
    before it."""
    messages = bag.messages(topics=topics)
    while True:
        with _readable(bag.path, f"after {sum(stats.published.values())} messages"):
            item = next(messages, None)
        if item is None:
            return
        yield item


def _clock_message(stamp_ns: int):
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock
    return Clock(clock=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000))
