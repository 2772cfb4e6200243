"""odg bag: MCAP bags of a tiny hand-made nuScenes dataroot, read back with iter_bag (no rclpy)."""
from __future__ import annotations

import dataclasses
import io
import subprocess
import sys

import numpy as np
import pytest
import yaml
from PIL import Image

from testing import tiny_nuscenes
from odg_ros import geometry
from odg_ros.bags import layout
from odg_ros.bags.bag_messages import deserialize, ego_twists
from odg_ros.bags.reader import bag_topics, iter_bag
from odg_ros.bags.writer import write_scene_bag
from odg_ros.bags.nuscenes_source import NuScenesSensorTables


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_nuscenes")
    expected = tiny_nuscenes.build(root)
    return root, expected


@pytest.fixture(scope="module")
def bags(world, tmp_path_factory):
    """Both scenes through the real command line (one bag folder per scene)."""
    root, _ = world
    out = tmp_path_factory.mktemp("bags") / "tiny"
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "bag", "nuscenes",
                             "--dataroot", str(root), "--out", str(out)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return out


def test_bag_tools_do_not_import_torch():
    """Writing, reading and laying out bags stays light: odg bag / odg replay never load torch."""
    code = ("import sys, odg_ros.bags.writer, odg_ros.bags.reader, odg_ros.bags.nuscenes_source; "
            "print('torch' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"


def test_counts_per_topic_and_metadata(world, bags):
    _, expected = world
    for scene, exp in expected.items():
        topics = bag_topics(bags / scene)
        assert {t: info.count for t, info in topics.items()} == exp["counts"]
        meta = yaml.safe_load((bags / scene / "metadata.yaml").read_text())
        info = meta["rosbag2_bagfile_information"]
        assert info["storage_identifier"] == "mcap"
        assert info["message_count"] == sum(exp["counts"].values())
        assert info["starting_time"]["nanoseconds_since_epoch"] == exp["start_us"] * 1000
        assert [f for f in info["relative_file_paths"]] == [f"{scene}.mcap"]
        assert (bags / scene / f"{scene}.mcap").is_file()
        # QoS as replay and `ros2 bag play` will offer it.
        assert topics["/tf_static"].qos == layout.TF_STATIC_QOS
        assert topics["/CAM_FRONT/image_rect_compressed"].qos.reliable is False
        assert topics["/odom"].qos.reliable is True


def test_stamps_ordered_and_from_nuscenes_microseconds(world, bags):
    root, expected = world
    tables = NuScenesSensorTables(root)
    for scene in expected:
        stamps = []
        for topic, log_ns, msgtype, raw in iter_bag(bags / scene):
            msg = deserialize(raw, msgtype)
            header = msg.transforms[0].header if msgtype == layout.TF_TYPE else msg.header
            header_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
            assert header_ns == log_ns
            assert log_ns % 1000 == 0  # microsecond stamps
            stamps.append(log_ns)
        assert stamps == sorted(stamps)
        records = tables.scene_records(scene)
        image_stamps = {r.timestamp_us * 1000 for r in records if r.channel != "LIDAR_TOP"}
        assert image_stamps <= set(stamps)


def test_jpeg_bytes_decode_to_the_written_image(world, bags):
    _, expected = world
    scene = "scene-0001"
    exp = expected[scene]
    frame = 0
    topic = "/CAM_BACK_LEFT/image_rect_compressed"
    for _, _, msgtype, raw in iter_bag(bags / scene, topics=[topic]):
        msg = deserialize(raw, msgtype)
        assert msg.format == "jpeg" and msg.header.frame_id == "CAM_BACK_LEFT"
        image = np.asarray(Image.open(io.BytesIO(msg.data.tobytes())).convert("RGB"), np.int32)
        assert image.shape == (tiny_nuscenes.HEIGHT, tiny_nuscenes.WIDTH, 3)
        want = tiny_nuscenes.colour(exp["scene_index"], 4, frame)
        assert np.abs(image.reshape(-1, 3).mean(0) - want).max() < 3
        frame += 1
    assert frame == exp["counts"]["/CAM_BACK_LEFT/image_rect_compressed"]


def test_tf_equals_ego_pose_and_static_equals_calibration(world, bags):
    root, _ = world
    scene = "scene-0001"
    records = NuScenesSensorTables(root).scene_records(scene)
    pose_by_ns = {r.timestamp_us * 1000: r.T_global_from_ego for r in records}
    calib = {r.channel: r.T_ego_from_sensor for r in records}

    def to_matrix(tf):
        q = tf.transform.rotation
        t = tf.transform.translation
        return geometry.make_transform([q.w, q.x, q.y, q.z], [t.x, t.y, t.z])

    checked = 0
    for topic, log_ns, msgtype, raw in iter_bag(bags / scene, topics=["/tf", "/tf_static"]):
        msg = deserialize(raw, msgtype)
        if topic == "/tf_static":
            assert {tf.child_frame_id for tf in msg.transforms} == set(calib)
            for tf in msg.transforms:
                assert tf.header.frame_id == "base_link"
                np.testing.assert_allclose(to_matrix(tf), calib[tf.child_frame_id], atol=1e-9)
        else:
            (tf,) = msg.transforms
            assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
            np.testing.assert_allclose(to_matrix(tf), pose_by_ns[log_ns], atol=1e-9)
            checked += 1
    assert checked == len(pose_by_ns)


def test_odometry_twist_and_camera_info(world, bags):
    scene = "scene-0001"
    odoms = [deserialize(raw, t) for _, _, t, raw in iter_bag(bags / scene, topics=["/odom"])]
    assert odoms[0].header.frame_id == "map" and odoms[0].child_frame_id == "base_link"
    inner = odoms[5:-5]  # central differences; the ends are one-sided
    lin = np.array([[o.twist.twist.linear.x, o.twist.twist.linear.y] for o in inner])
    ang = np.array([o.twist.twist.angular.z for o in inner])
    np.testing.assert_allclose(lin[:, 0], tiny_nuscenes.SPEED, rtol=1e-3)
    np.testing.assert_allclose(lin[:, 1], 0.0, atol=0.05)
    np.testing.assert_allclose(ang, tiny_nuscenes.YAW_RATE, rtol=1e-5)

    _, _, msgtype, raw = next(iter_bag(bags / scene, topics=["/CAM_FRONT/camera_info"]))
    info = deserialize(raw, msgtype)
    assert (info.width, info.height) == (tiny_nuscenes.WIDTH, tiny_nuscenes.HEIGHT)
    K = info.k.reshape(3, 3)
    np.testing.assert_allclose(K, [[40, 0, 32], [0, 40, 18], [0, 0, 1]])
    np.testing.assert_allclose(info.p.reshape(3, 4)[:, :3], K)
    assert info.header.frame_id == "CAM_FRONT"


def test_point_cloud_matches_the_sweep(world, bags):
    root, _ = world
    records = [r for r in NuScenesSensorTables(root).scene_records("scene-0002")
               if r.channel == "LIDAR_TOP"]
    clouds = list(iter_bag(bags / "scene-0002", topics=["/LIDAR_TOP"]))
    assert len(clouds) == len(records)
    msg = deserialize(clouds[3][3], clouds[3][2])
    points = np.frombuffer(msg.data.tobytes(), np.float32).reshape(msg.height * msg.width, 5)
    np.testing.assert_array_equal(points, np.fromfile(records[3].path, np.float32).reshape(-1, 5))
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "ring"]


def test_single_scene_without_lidar_and_refusals(world, tmp_path):
    root, expected = world
    out = tmp_path / "one"
    tables = NuScenesSensorTables(root)
    summary = write_scene_bag(tables.scene_records("scene-0002", with_lidar=False), out,
                              progress=False)
    want = {t: n for t, n in expected["scene-0002"]["counts"].items() if t != "/LIDAR_TOP"}
    # Without the LiDAR there are fewer distinct pose stamps.
    cams = [r for r in tables.scene_records("scene-0002", with_lidar=False)]
    want["/tf"] = want["/odom"] = len({r.timestamp_us for r in cams})
    assert summary.counts == want
    with pytest.raises(FileExistsError, match="--force"):
        write_scene_bag(cams, out, progress=False)
    write_scene_bag(cams, out, progress=False, force=True)
    with pytest.raises(KeyError, match="scene-9999"):
        tables.scene_records("scene-9999")


def test_missing_image_fails_cleanly(world, tmp_path):
    root, _ = world
    records = NuScenesSensorTables(root).scene_records("scene-0002", with_lidar=False)
    broken = [r if i != 10 else dataclasses.replace(r, path=tmp_path / "nope.jpg")
              for i, r in enumerate(records)]
    with pytest.raises(FileNotFoundError, match="nope.jpg"):
        write_scene_bag(broken, tmp_path / "bag", progress=False)
    assert not (tmp_path / "bag").exists()  # no partial bag left behind


def test_command_line_errors(tmp_path):
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "bag", "nuscenes",
                             "--dataroot", str(tmp_path / "missing"), "--out", str(tmp_path / "b")],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "dataroot not found" in result.stderr


def _reference_twist(t, T, i, half=0.1):
    """Per-index float64 reference of ego_twists with plain loops and the axis-angle formula."""
    n = len(t)
    a = min(range(n), key=lambda j: (abs(t[j] - (t[i] - half)), j))
    b = min(range(n), key=lambda j: (abs(t[j] - (t[i] + half)), j))
    if i > 0:
        a = min(a, i - 1)
    if i < n - 1:
        b = max(b, i + 1)
    dt = t[b] - t[a]
    v = T[i][:3, :3].T @ (T[b][:3, 3] - T[a][:3, 3]) / dt
    R_rel = T[a][:3, :3].T @ T[b][:3, :3]
    angle = np.arccos(np.clip((np.trace(R_rel) - 1) / 2, -1, 1))
    axis = np.array([R_rel[2, 1] - R_rel[1, 2], R_rel[0, 2] - R_rel[2, 0],
                     R_rel[1, 0] - R_rel[0, 1]])
    w = np.zeros(3) if angle < 1e-12 else axis / (2 * np.sin(angle)) * angle / dt
    return v, w


def test_ego_twists_against_reference_and_hard_cases():
    rng = np.random.default_rng(0)
    times_us = np.cumsum(rng.integers(3_000, 60_000, size=40))
    # Smooth random motion (rotations < pi between neighbours, as for a real vehicle).
    yaw_pitch_roll = np.cumsum(rng.normal(scale=0.05, size=(40, 3)), axis=0)
    from scipy.spatial.transform import Rotation
    T = np.stack([geometry.make_transform(Rotation.from_euler("zyx", e).as_matrix(), p)
                  for e, p in zip(yaw_pitch_roll, np.cumsum(rng.normal(size=(40, 3)), axis=0))])
    linear, angular = ego_twists(times_us, T)
    for i in range(len(times_us)):
        v, w = _reference_twist(times_us * 1e-6, T, i)
        np.testing.assert_allclose(linear[i], v, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(angular[i], w, rtol=1e-7, atol=1e-9)

    single_linear, single_angular = ego_twists([5], T[:1])
    assert not single_linear.any() and not single_angular.any()
    two_linear, _ = ego_twists([0, 500_000], T[:2])  # both ends one-sided, same pair
    np.testing.assert_allclose(two_linear[0], T[0][:3, :3].T @ (T[1][:3, 3] - T[0][:3, 3]) / 0.5)
    with pytest.raises(ValueError, match="increasing"):
        ego_twists([0, 0], T[:2])
    bad = T[:3].copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        ego_twists([0, 1, 2], bad)


def test_mcap_is_readable_by_an_independent_ros2_decoder(world, bags):
    """What rosbag2's MCAP storage plugin needs: ros2 profile, ros2msg schemas, cdr channels
    with offered QoS, the rosbag2 metadata record; every message decodes with mcap_ros2."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    _, expected = world
    scene = "scene-0002"
    with open(bags / scene / f"{scene}.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        for channel in summary.channels.values():
            assert channel.message_encoding == "cdr"
            assert summary.schemas[channel.schema_id].encoding == "ros2msg"
            assert "offered_qos_profiles" in channel.metadata
        assert any(m.name == "rosbag2" for m in reader.iter_metadata())
        counts = {}
        for _, channel, message, decoded in reader.iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == "/odom":
                assert decoded.child_frame_id == "base_link"
                assert message.log_time == message.publish_time
    assert counts == expected[scene]["counts"]


def test_bag_of_the_synthetic_world(tmp_path):
    """`odg bag synth` on a world from the synth generator: one message per sample_data of
    each channel, the JPEG bytes as on disk, /tf equal to the ego poses of the tables."""
    import json

    from odg_ros.data.synth.generate import generate

    world = tmp_path / "world"
    generate(str(world), scenes=1, seconds=1.0, image_hw=(45, 80), progress=False)
    out = tmp_path / "synth_bag"
    result = subprocess.run([sys.executable, "-m", "odg_ros.commands", "bag", "synth",
                             "--world", str(world), "--out", str(out)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr

    version = next(p for p in world.iterdir() if (p / "scene.json").is_file())
    sample_data = json.loads((version / "sample_data.json").read_text())
    calib = {c["token"]: c for c in json.loads((version / "calibrated_sensor.json").read_text())}
    sensors = {s["token"]: s["channel"] for s in json.loads((version / "sensor.json").read_text())}
    poses = {p["token"]: p for p in json.loads((version / "ego_pose.json").read_text())}
    by_channel = {}
    for sd in sample_data:
        by_channel.setdefault(sensors[calib[sd["calibrated_sensor_token"]]["sensor_token"]],
                              []).append(sd)
    counts = {t: info.count for t, info in bag_topics(out).items()}
    for channel, rows in by_channel.items():
        topic = "/LIDAR_TOP" if channel == "LIDAR_TOP" else layout.image_topic(channel)
        assert counts[topic] == len(rows), channel
    front = sorted(by_channel["CAM_FRONT"], key=lambda r: r["timestamp"])
    images = [deserialize(raw, t) for _, _, t, raw in
              iter_bag(out, topics=[layout.image_topic("CAM_FRONT")])]
    for row, msg in zip(front, images):
        assert msg.data.tobytes() == (world / row["filename"]).read_bytes()
    tf_by_ns = {ns: deserialize(raw, t).transforms[0].transform
                for _, ns, t, raw in iter_bag(out, topics=["/tf"])}
    for row in front:
        pose = poses[row["ego_pose_token"]]
        tf = tf_by_ns[row["timestamp"] * 1000]
        np.testing.assert_allclose([tf.translation.x, tf.translation.y, tf.translation.z],
                                   pose["translation"], atol=1e-9)
        q = [tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z]
        np.testing.assert_allclose(geometry.quaternion_to_matrix(q),
                                   geometry.quaternion_to_matrix(pose["rotation"]), atol=1e-9)
