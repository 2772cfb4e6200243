"""Read rosbag2 bags (no rclpy): their topics with the recorded QoS, and their messages as
``(topic, log_time_ns, msgtype, cdr_bytes)``.

``open_bag`` takes what users have on disk:

* a bag folder with ``metadata.yaml`` (MCAP or SQLite 3), read with rosbags in log-time order;
* a recording that ended badly: an MCAP file without its summary, footer or end magic (the
  recorder was killed, the disk filled up, a copy was cut short). rosbag2 writes
  ``metadata.yaml`` and the MCAP summary only when it closes the bag, so such a recording is a
  folder of ``*.mcap`` files without ``metadata.yaml``, or a folder whose MCAP file rosbags
  refuses (``File end magic is invalid``). Its messages are read in file order (there is no
  index to sort them by; rosbag2 falls back to file order too) up to the first record that is
  cut or damaged, and ``Bag.damage`` says how much that is;
* a single ``.mcap`` file, or a folder of complete ones without ``metadata.yaml``, read in
  log-time order by their index.

``find_bags`` turns a path into the bags it names: a bag, or a folder of bags (its
sub-folders that are bags, in name order).
"""
from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from . import layout


@dataclass(frozen=True)
class BagTopic:
    name: str
    msgtype: str
    count: int
    qos: layout.TopicQos | None  # the offered QoS recorded in the bag, None when absent


@dataclass
class Bag:
    """One bag opened for reading. ``damage`` is None for a complete bag, else one line
    saying what could be read of a recording that ended badly (messages, seconds of bag
    time, bytes)."""

    path: Path
    topics: dict[str, BagTopic]
    message_count: int
    start_ns: int | None
    end_ns: int | None
    damaged_at: str | None = None     # where and why reading a bag that ended badly stopped
    recorded_count: int | None = None  # messages its metadata.yaml lists, if it has one
    _mcap_files: list[Path] = field(default_factory=list, repr=False)

    @property
    def damage(self) -> str | None:
        """None for a complete bag, else one line: what could be read of it."""
        if self.damaged_at is None:
            return None
        what = (f"{self.path} ended badly ({self.damaged_at}; no MCAP summary: the recorder "
                "was killed or the file was cut short)")
        if not self.message_count:
            return f"{what}: not one message is complete"
        read = (f"{self.message_count} of {self.recorded_count}"
                if self.recorded_count is not None else f"{self.message_count}")
        return (f"{what}: replaying the {read} messages before that, "
                f"{self.duration_s:.2f} s of bag time")

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) * 1e-9

    def messages(self, topics: Iterable[str] | None = None
                 ) -> Iterator[tuple[str, int, str, bytes]]:
        """``(topic, log_time_ns, msgtype, cdr_bytes)``: log-time order for a complete bag,
        file order up to the damage for one that ended badly."""
        wanted = None if topics is None else set(topics)
        if not self._mcap_files:
            yield from _rosbags_messages(self.path, wanted)
            return
        source = (_stream_messages(self._mcap_files) if self.damaged_at is not None
                  else _indexed_messages(self._mcap_files))
        for topic, log_ns, msgtype, raw in source:
            if wanted is None or topic in wanted:
                yield topic, log_ns, msgtype, raw


def is_bag_folder(path: Path) -> bool:
    """A rosbag2 folder: ``metadata.yaml``, or (a recording that ended badly) MCAP files."""
    path = Path(path)
    return path.is_dir() and ((path / "metadata.yaml").is_file()
                              or any(path.glob("*.mcap")))


def find_bags(path) -> list[Path]:
    """The bags ``path`` names: itself (a bag folder or an ``.mcap`` file), or the bags in
    it (sub-folders that are bags, or ``.mcap`` files, in name order)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} not found")
    if path.is_file():
        if path.suffix == ".mcap":
            return [path]
        raise ValueError(f"{path} is not a rosbag2 bag (give its folder, or an .mcap file)")
    if is_bag_folder(path):
        return [path]
    bags = sorted(p for p in path.iterdir() if is_bag_folder(p))
    if not bags:
        raise ValueError(f"{path} is not a rosbag2 bag (no metadata.yaml or .mcap file) and "
                         "holds none")
    return bags


def open_bag(path) -> Bag:
    """A bag folder or ``.mcap`` file, opened (see the module docstring). Raises
    FileNotFoundError for a path that does not exist and ValueError for one that is no
    readable bag."""
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} not found")
    if path.is_file():
        if path.suffix != ".mcap":
            raise ValueError(f"{path} is not a rosbag2 bag (give its folder, or an .mcap file)")
        return _open_stream(path, [path])
    metadata = path / "metadata.yaml"
    if not metadata.is_file():
        files = sorted(path.glob("*.mcap"))
        if not files:
            raise ValueError(f"{path} is not a rosbag2 folder (no metadata.yaml)")
        return _open_stream(path, files)
    try:
        with Reader(path) as reader:
            return _rosbags_bag(path, reader)
    except Exception as error:   # what the reader raises on bytes it cannot parse
        files = _listed_mcap_files(metadata)
        if files and all(f.is_file() for f in files):
            bag = _open_stream(path, files)
            if bag.damage is not None:
                return bag
        raise ValueError(f"{path} is not a readable rosbag2 bag (cannot open it: "
                         f"{type(error).__name__}: {error})") from error


def bag_topics(path) -> dict[str, BagTopic]:
    """Topics of a bag with their recorded QoS."""
    return open_bag(path).topics


def iter_bag(path, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, str, bytes]]:
    """Yield ``(topic, log_time_ns, msgtype, cdr_bytes)`` of a bag (``Bag.messages``)."""
    return open_bag(path).messages(topics)


# ---------------------------------------------------------------------------------------------
# Complete bags: rosbags


def _topic_qos(conn) -> layout.TopicQos | None:
    from rosbags.interfaces import QosDurability, QosReliability

    profiles = getattr(conn.ext, "offered_qos_profiles", None) or []
    if not profiles:
        return None
    p = profiles[0]
    return layout.TopicQos(reliable=p.reliability != QosReliability.BEST_EFFORT,
                           transient_local=p.durability == QosDurability.TRANSIENT_LOCAL,
                           depth=max(1, int(p.depth or 1)))


def _rosbags_bag(path: Path, reader) -> Bag:
    topics: dict[str, BagTopic] = {}
    for conn in reader.connections:
        previous = topics.get(conn.topic)
        count = conn.msgcount + (previous.count if previous else 0)
        topics[conn.topic] = BagTopic(conn.topic, conn.msgtype, count, _topic_qos(conn))
    count = sum(t.count for t in topics.values())
    start = reader.start_time if count else None
    end = reader.end_time - 1 if count else None    # rosbags: one past the last message
    return Bag(path, topics, count, start, end)


def _rosbags_messages(path: Path, wanted: set[str] | None):
    from rosbags.rosbag2 import Reader

    with Reader(path) as reader:
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not connections:
            return
        for conn, timestamp, raw in reader.messages(connections=connections):
            yield conn.topic, int(timestamp), conn.msgtype, bytes(raw)


# ---------------------------------------------------------------------------------------------
# Recordings that ended badly: MCAP read as a stream, up to the damage


def _listed_mcap_files(metadata: Path) -> list[Path]:
    """The MCAP files a metadata.yaml names ([] if it names none or is unreadable)."""
    try:
        info = yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]
        if info.get("storage_identifier") != "mcap":
            return []
        return [metadata.parent / Path(p).name for p in info["relative_file_paths"]]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return []


class _Progress:
    """How far a stream of MCAP files was read: the file and byte offset after the last
    complete record, and why reading stopped (None: every file read to its end magic)."""

    def __init__(self):
        self.file: Path | None = None
        self.offset = 0
        self.size = 0
        self.problem: str | None = None


def _stream_records(files: list[Path], progress: _Progress):
    """(schemas, channels, Message) of each file in order, until the first damaged one."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, Footer, Message, Schema
    from mcap.stream_reader import StreamReader

    for path in files:
        progress.file, progress.offset, progress.size = path, 0, path.stat().st_size
        schemas, channels = {}, {}
        with open(path, "rb") as f:
            reader = StreamReader(f, validate_crcs=True, record_size_limit=2**31)
            finished = False
            try:
                for record in reader.records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Message):
                        channel = channels.get(record.channel_id)
                        if channel is None:
                            raise ValueError(f"message on unknown channel {record.channel_id}")
                        schema = schemas.get(channel.schema_id)
                        yield channel.topic, record.log_time, \
                            schema.name if schema is not None else "", record.data
                    elif isinstance(record, Footer):
                        finished = True
                    progress.offset = f.tell()
            except (EndOfFile, struct.error):       # a record cut short
                progress.problem = "the file ends inside a record"
                return
            except Exception as error:    # a damaged record: stop here
                progress.problem = f"{type(error).__name__}: {error}"
                return
            if not finished:
                progress.problem = "the file ends without a footer"
                return


def _stream_messages(files: list[Path]):
    yield from _stream_records(files, _Progress())


def _indexed_messages(files: list[Path]):
    """Complete MCAP files without metadata.yaml: each in log-time order by its index."""
    from mcap.reader import make_reader

    for path in files:
        with open(path, "rb") as f:
            for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
                yield channel.topic, message.log_time, schema.name if schema else "", \
                    message.data


def _open_stream(path: Path, files: list[Path]) -> Bag:
    """Scan MCAP files as a stream: their topics, counts and time span up to the damage."""
    progress = _Progress()
    topics: dict[str, list] = {}
    count, start, end = 0, None, None
    for topic, log_ns, msgtype, _ in _stream_records(files, progress):
        entry = topics.setdefault(topic, [msgtype, 0])
        entry[1] += 1
        count += 1
        start = log_ns if start is None else min(start, log_ns)
        end = log_ns if end is None else max(end, log_ns)
    bag = Bag(path, {t: BagTopic(t, msgtype, n, None) for t, (msgtype, n) in topics.items()},
              count, start, end, _mcap_files=list(files))
    if progress.problem is not None:
        where = progress.file.name if progress.file is not None else path.name
        bag.damaged_at = (f"{progress.problem} at byte {progress.offset} of {progress.size} "
                          f"of {where}")
        bag.recorded_count = _listed_count(path / "metadata.yaml") if path.is_dir() else None
    return bag


def _listed_count(metadata: Path) -> int | None:
    """The message count a metadata.yaml gives (None if there is none)."""
    try:
        return int(yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]
                   ["message_count"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None
