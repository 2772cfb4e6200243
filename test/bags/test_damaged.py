"""Recordings that ended badly: an MCAP bag cut at byte offsets all through the file (inside
the header, mid-chunk, at a chunk's end, in the message index, in the summary, the end magic)
reads up to the last complete chunk, byte-exact, with one line saying how much that is; with
its metadata.yaml (rosbags refuses the file), without it (the recorder was killed before it
wrote one) and as a bare .mcap file. The expected messages come from the intact file's chunk
index (no rclpy)."""
from __future__ import annotations

import shutil

import pytest

from odg_ros.bags.reader import find_bags, open_bag
from odg_ros.bags.writer import write_scene_bag
from odg_ros.bags.nuscenes_source import NuScenesSensorTables
from testing import tiny_nuscenes


@pytest.fixture(scope="module")
def intact(tmp_path_factory):
    """A 12-s scene: three MCAP chunks (rosbags closes a chunk past 1 MiB)."""
    root = tmp_path_factory.mktemp("tiny_nuscenes")
    tiny_nuscenes.build(root, scene_durations_s=(12.0,))
    out = tmp_path_factory.mktemp("bags") / "scene-0001"
    write_scene_bag(NuScenesSensorTables(root).scene_records("scene-0001"), out, progress=False)
    return out


def chunks_of(mcap_path):
    """[(end offset of the chunk record, [(topic, log_time, data) of its messages])] in file
    order, from the intact file's summary (chunk index)."""
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk
    from mcap.data_stream import ReadDataStream

    with open(mcap_path, "rb") as f:
        summary = make_reader(f).get_summary()
        channels = dict(summary.channels)
        result = []
        for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            f.seek(index.chunk_start_offset + 9)            # opcode (1) + record length (8)
            chunk = Chunk.read(ReadDataStream(f))
            messages = [(channels[r.channel_id].topic, r.log_time, r.data)
                        for r in breakup_chunk(chunk) if isinstance(r, Message)]
            result.append((index.chunk_start_offset + index.chunk_length, messages))
    assert len(result) == 3, "the fixture must span several chunks"
    return result


def cut_offsets(chunks, size):
    """Named byte offsets to cut the file at, with the chunks complete before each."""
    (end1, _), (end2, _), (end3, _) = chunks
    start2 = end1 + (end2 - end1) // 10          # in the message index after chunk 1 or so
    return {
        "inside the header": 20,
        "mid first chunk": end1 // 2,
        "at the first chunk's end": end1,
        "after the first chunk's index": start2,
        "mid second chunk": (end1 + end2) // 2,
        "mid third chunk": (end2 + end3) // 2,
        "in the summary": (end3 + size) // 2,
        "without the end magic": size - 4,
    }


def expected_messages(chunks, offset):
    return [m for end, messages in chunks if end <= offset for m in messages]


@pytest.mark.parametrize("form", ["with metadata.yaml", "without metadata.yaml", "bare .mcap"])
def test_a_cut_recording_reads_up_to_the_damage(intact, tmp_path, form):
    mcap = next(intact.glob("*.mcap"))
    data = mcap.read_bytes()
    chunks = chunks_of(mcap)
    intact_bag = open_bag(intact)
    assert intact_bag.damage is None
    total = intact_bag.message_count
    for name, offset in cut_offsets(chunks, len(data)).items():
        bag_dir = tmp_path / name.replace(" ", "_").replace("'", "")
        shutil.copytree(intact, bag_dir)
        cut = bag_dir / mcap.name
        cut.write_bytes(data[:offset])
        if form != "with metadata.yaml":
            (bag_dir / "metadata.yaml").unlink()
        path = cut if form == "bare .mcap" else bag_dir
        assert find_bags(path) == [path]
        bag = open_bag(path)
        want = expected_messages(chunks, offset)
        got = [(topic, log_ns, raw) for topic, log_ns, _, raw in bag.messages()]
        assert got == want, name
        assert bag.message_count == len(want), name
        assert bag.damage is not None, name
        assert "ended badly" in bag.damage and f"of {len(data[:offset])}" in bag.damage
        read = f"{len(want)} of {total}" if form == "with metadata.yaml" else f"{len(want)}"
        if not want:
            assert bag.damage.endswith("not one message is complete"), (name, bag.damage)
        else:
            assert f"the {read} messages" in bag.damage, (name, bag.damage)
            times = [t for _, t, _ in want]
            assert (bag.start_ns, bag.end_ns) == (min(times), max(times))
            assert f"{(max(times) - min(times)) * 1e-9:.2f} s of bag time" in bag.damage
            assert sum(t.count for t in bag.topics.values()) == len(want)
            types = {t: info.msgtype for t, info in intact_bag.topics.items()}
            assert {t: info.msgtype for t, info in bag.topics.items()} == \
                {t: types[t] for t, _, _ in want}


def test_an_intact_bag_without_metadata_reads_whole_and_quietly(intact, tmp_path):
    """An MCAP with its summary but no metadata.yaml (copied alone) is no damage."""
    bag_dir = tmp_path / "alone"
    shutil.copytree(intact, bag_dir)
    (bag_dir / "metadata.yaml").unlink()
    bag = open_bag(bag_dir)
    assert bag.damage is None
    assert bag.message_count == open_bag(intact).message_count
    assert [m[3] for m in bag.messages()] == [m[3] for m in open_bag(intact).messages()]


def test_paths_that_are_no_bag(tmp_path, intact):
    with pytest.raises(FileNotFoundError, match="not found"):
        open_bag(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="not found"):
        find_bags(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no metadata.yaml or .mcap file"):
        find_bags(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ValueError, match="not a rosbag2 bag"):
        find_bags(tmp_path / "notes.txt")
    # a folder of bags: its bags in name order
    folder = tmp_path / "scenes"
    for name in ("b", "a"):
        shutil.copytree(intact, folder / name)
    (folder / "readme").mkdir()
    assert find_bags(folder) == [folder / "a", folder / "b"]
