"""Hard cases of the node's geometry inputs on the ROS-free core: a hostile TF tree (loops,
stray dynamic copies of static links, floods of frame names), implausible calibration and
poses (a focal length of 1e300, a pose sample 1 km off, a teleport), invalid header stamps
and decompression bombs.

The contract: a bad message is rejected and counted, never interpolated into a camera pose
or decoded whole; the tree and the buffers stay usable; memory stays bounded; after the fault
stops the next clean set gives the same grid as without the fault.
"""
import io
import zlib

import numpy as np
import PIL.ImageFile
import pytest
import torch
from PIL import Image

from testing.helpers import tiny_config
from odg_ros.geometry import make_transform
from odg_ros.network import ODG
from odg_ros.online import diagnostics
from odg_ros.online.errors import BadInput
from odg_ros.online.history import Frame, FrameHistory
from odg_ros.online.images import EncodedImage, decode_for_input
from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings
from odg_ros.online.poses import PoseBuffer
from odg_ros.online.predictor import OnlinePredictor
from odg_ros.online.camera_calibration import check_intrinsics
from odg_ros.online.sync import stamp_to_seconds
from odg_ros.online.transforms import TransformBuffer
from testing.online import CAMS, HW, OFFSETS, RIG, feed_set, png, scaled_K, set_images


def pose_at(t):
    """10 m/s along x, turning slowly."""
    yaw = 0.02 * t
    return make_transform([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)], (10.0 * t, 0.1 * t, 0.0))


def kind_of(call, *args, **kwargs):
    try:
        call(*args, **kwargs)
    except BadInput as error:
        return error.kind
    return "ok"


def shifted(T, dx):
    T = T.copy()
    T[0, 3] += dx
    return T


# ------------------------------------------------------------------------- TF tree
def test_a_loop_link_is_rejected_and_the_tree_stays_usable():
    tf = TransformBuffer()
    for t in np.arange(10.0, 11.0, 0.02):
        tf.add("map", "base_link", float(t), pose_at(float(t)))
    assert kind_of(tf.add, "base_link", "map", 10.5, np.eye(4)) == "bad_tf"
    tf.add("odom", "map", 10.5, np.eye(4), static=True)       # extends the tree upwards
    assert kind_of(tf.add, "base_link", "odom", 10.5, np.eye(4), static=True) == "bad_tf"
    for t in np.arange(11.0, 12.0, 0.02):
        tf.add("map", "base_link", float(t), pose_at(float(t)))
    assert np.allclose(tf.lookup("map", "base_link", 11.51), pose_at(11.51), atol=1e-3)


def test_a_dynamic_copy_never_removes_a_static_link():
    tf = TransformBuffer()
    base_from_cam = RIG.cameras["CAM_FRONT"].sensor2ego
    tf.add("base_link", "CAM_FRONT", 0.0, base_from_cam, static=True)
    tf.add("base_link", "CAM_FRONT", 10.0, base_from_cam)     # one stray copy on /tf
    for t in (10.0, 15.0, 100.0):
        assert np.allclose(tf.lookup("base_link", "CAM_FRONT", t, "missing_extrinsics"),
                           base_from_cam)


def test_frames_not_updated_for_the_buffer_duration_are_forgotten():
    clock = [0.0]
    tf = TransformBuffer(cache_time=10.0, clock=lambda: clock[0])
    for k in range(2000):                                       # a stream of new names
        tf.add("map", f"tracked_object_{k}", 1.0, np.eye(4))
        clock[0] += 0.004                                       # 8 s in all
    assert len(tf.frames()) == 2001
    for k in range(30):                                         # base_link keeps updating
        tf.add("map", "base_link", 20.0 + k, np.eye(4))
        clock[0] += 1.0
    assert tf.frames() == {"map", "base_link"}
    assert tf.counters["tf_frames_forgotten"] == 2000


def test_only_the_needed_chains_are_converted_the_rest_dropped_by_name():
    tf = TransformBuffer(wanted={"base_link", "CAM_FRONT"})
    assert tf.wants("base_link") and tf.wants("CAM_FRONT") and not tf.wants("map")
    tf.add("odom", "base_link", 1.0, np.eye(4))
    assert tf.wants("odom")                                     # the chain up is learnt
    tf.add("map", "odom", 1.0, np.eye(4))
    assert tf.wants("map")
    busy = [f"fixed_frame_{k}" for k in range(250)]
    assert not any(tf.wants(name) for name in busy)
    assert tf.counters["tf_ignored"] == 251       # map before it was needed + the 250
    assert tf.counters["tf_received"] == 255
    # a sensor's first /tf before its CameraInfo named its frame: kept as a child of the ego
    tf.keep_children_of({"base_link"})
    assert tf.wants("CAM_BACK", "base_link") and not tf.wants("fixed_frame_0", "world")


# ------------------------------------------------------------------ plausibility
def test_implausible_intrinsics_are_rejected():
    K = scaled_K("CAM_FRONT")
    assert check_intrinsics(K, *HW).image_hw == HW
    for name, calibration in RIG.cameras.items():              # the shipped rig passes
        check_intrinsics(calibration.intrinsics, *calibration.image_hw)
    for fx in (1e300, 1e-3, 1e5):
        bad = K.copy()
        bad[0, 0] = bad[1, 1] = fx
        assert kind_of(check_intrinsics, bad, *HW) == "implausible_camera_info", fx
    far = K.copy()
    far[0, 2] = 10 * HW[1]
    assert kind_of(check_intrinsics, far, *HW) == "implausible_camera_info"


@pytest.mark.parametrize("offset", [1000.0, 1e300])
def test_a_pose_glitch_is_rejected_and_never_interpolated(offset):
    buffer = PoseBuffer(max_speed=70.0, max_acceleration=30.0)
    for t in np.arange(10.0, 12.0, 0.02):
        buffer.add(float(t), pose_at(float(t)))
    clean = buffer.lookup(11.031)
    assert kind_of(buffer.add, 11.03, shifted(pose_at(11.03), offset)) == "implausible_motion"
    assert np.array_equal(buffer.lookup(11.031), clean)
    buffer.add(12.0, pose_at(12.0))                            # the next sample is accepted
    assert buffer.teleports == 0 and len(buffer) == 101


def test_real_motion_with_noise_and_uneven_stamps_is_never_a_glitch():
    """Ego poses at every camera stamp (6 within 42 ms, then a 41 ms gap), 1 cm of noise,
    a car braking at 8 m/s^2 from 30 m/s, shuffled within each set."""
    rng = np.random.default_rng(0)
    buffer = PoseBuffer(max_speed=70.0, max_acceleration=30.0)
    for k in range(40):
        stamps = [k / 12 + o for o in (0.0, 0.008, 0.017, 0.025, 0.033, 0.042)]
        for t in rng.permutation(stamps):
            x = 30.0 * t - 4.0 * t * t
            buffer.add(float(t), make_transform([1, 0, 0, 0], (x, 0.0, 0.0))
                       @ make_transform([1, 0, 0, 0], rng.normal(0, 0.01, 3)))
    assert len(buffer) == 240 and buffer.teleports == 0


def test_a_jump_within_the_speed_limit_is_caught_by_the_acceleration():
    buffer = PoseBuffer(max_speed=70.0, max_acceleration=30.0)
    for t in np.arange(10.0, 11.0, 0.1):                      # 10 Hz at 10 m/s
        buffer.add(float(t), pose_at(float(t)))
    # 2 m ahead of where it should be: 30 m/s over the last 0.1 s, under max_speed
    assert kind_of(buffer.add, 11.0, shifted(pose_at(11.0), 2.0)) == "implausible_motion"
    buffer.add(11.0, pose_at(11.0))


def test_a_teleport_that_persists_restarts_the_buffer_and_the_history():
    buffer = PoseBuffer(max_speed=70.0, max_acceleration=30.0, teleport_samples=3)
    for t in np.arange(10.0, 11.0, 0.02):
        buffer.add(float(t), pose_at(float(t)))
    kinds = [kind_of(buffer.add, float(t), shifted(pose_at(float(t)), 1000.0))
             for t in np.arange(11.0, 11.1, 0.02)]
    assert kinds == ["implausible_motion", "implausible_motion", "ok", "ok", "ok"]
    assert buffer.teleports == 1 and buffer.span == pytest.approx((11.0, 11.08))
    assert np.allclose(buffer.lookup(11.05), shifted(pose_at(11.05), 1000.0), atol=1e-6)

    history = FrameHistory(capacity=4, max_gap=1.0, max_speed=70.0)
    for stamp, dx in ((10.0, 0.0), (10.5, 0.0), (11.0, 1000.0)):
        reason = history.push(Frame(None, shifted(pose_at(stamp), dx), np.eye(4)[None], stamp))
    assert reason == "teleport" and len(history) == 1 and history.resets["teleport"] == 1


def test_a_pose_glitch_on_tf_is_rejected_and_counted():
    tf = TransformBuffer(max_speed=70.0, max_acceleration=30.0)
    for t in np.arange(10.0, 12.0, 0.02):
        tf.add("map", "base_link", float(t), pose_at(float(t)))
    clean = tf.lookup("map", "base_link", 11.031)
    assert kind_of(tf.add, "map", "base_link", 11.03, shifted(pose_at(11.03), 1e300)) \
        == "implausible_motion"
    assert np.array_equal(tf.lookup("map", "base_link", 11.031), clean)


def test_header_stamps_must_be_valid_times():
    assert stamp_to_seconds(12, 500_000_000) == 12.5
    assert stamp_to_seconds(0, 999_999_999) == pytest.approx(1.0)
    for nanosec in (1_000_000_000, 4_000_000_000, -1):
        assert kind_of(stamp_to_seconds, 12, nanosec) == "bad_stamp"


# ------------------------------------------------------------------------- images
def png_declaring(height, width):
    """A small PNG whose IHDR declares height x width (valid CRC; the pixel data is short)."""
    data = bytearray(png(np.zeros((8, 8, 3), np.uint8)))
    ihdr = data.index(b"IHDR")
    data[ihdr + 4:ihdr + 12] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    data[ihdr + 17:ihdr + 21] = zlib.crc32(bytes(data[ihdr:ihdr + 17])).to_bytes(4, "big")
    return bytes(data)


def jpeg_declaring(height, width):
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(buffer, format="JPEG")
    data = bytearray(buffer.getvalue())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    return bytes(data)


def test_image_size_is_checked_from_the_header_before_decoding(monkeypatch):
    def no_decoding(self):
        raise AssertionError("pixels decoded")

    monkeypatch.setattr(PIL.ImageFile.ImageFile, "load", no_decoding)
    bomb = EncodedImage(True, "png", png_declaring(8000, 8000))
    assert kind_of(decode_for_input, bomb, (64, 176), max_pixels=4096 * 4096) \
        == "image_too_large"
    assert kind_of(decode_for_input, EncodedImage(True, "jpeg", jpeg_declaring(8000, 8000)),
                   (64, 176), max_pixels=4096 * 4096) == "image_too_large"
    assert kind_of(decode_for_input, EncodedImage(True, "jpeg", jpeg_declaring(900, 1600)),
                   (64, 176), expected_hw=HW) == "wrong_image_size"
    raw = EncodedImage(False, "rgb8", b"", 8000, 8000, 24000)
    assert kind_of(decode_for_input, raw, (64, 176), max_pixels=4096 * 4096) \
        == "image_too_large"


# -------------------------------------------------------------------- diagnostics
def test_no_output_while_inputs_arrive_is_an_error_with_the_dominant_reason():
    clock = [0.0]
    stats = diagnostics.PipelineStats(stale_after_s=5.0, clock=lambda: clock[0])
    counters = {"sets_completed": 0, "pose_miss": 0, "corrupt_image": 0}
    stats.record_output(0.0, 0.1, {})
    levels = []
    for second in range(1, 13):       # 2 sets/s, all pose misses but one corrupt image
        clock[0] = float(second)
        counters["sets_completed"] += 2
        counters["pose_miss"] += 2 if second != 7 else 1
        counters["corrupt_image"] += 1 if second == 7 else 0
        status = stats.status(counters)
        levels.append(status["level"])
    assert levels[:4] == [diagnostics.WARN] * 4 and levels[-1] == diagnostics.ERROR
    assert "no output for 12.0 s while inputs arrive" in status["message"]
    assert "92 % of dropped sets and inputs were pose_miss (11 of 12)" in status["message"]
    clock[0] = 30.0                               # inputs stopped: not this error any more
    assert "while inputs arrive" not in stats.status(counters)["message"]

    # never an output: the timer runs from the first complete set, not from the start
    never = diagnostics.PipelineStats(stale_after_s=5.0, clock=lambda: clock[0])
    clock[0] += 6.0
    assert never.status({"sets_completed": 0, "missing_camera_info": 0})["level"] \
        == diagnostics.WARN
    never.record_complete_set()
    clock[0] += 4.0
    assert never.status({"sets_completed": 8, "missing_extrinsics": 8})["level"] \
        == diagnostics.WARN
    clock[0] += 2.0
    status = never.status({"sets_completed": 12, "missing_extrinsics": 12})
    assert status["level"] == diagnostics.ERROR
    assert "no output for 6.0 s while inputs arrive: 100 % of dropped sets and inputs were " \
        "missing_extrinsics" in status["message"]


def test_a_tf_flood_shows_in_diagnostics():
    clock = [0.0]
    stats = diagnostics.PipelineStats(clock=lambda: clock[0], max_tf_rate=1000.0)
    stats.record_output(0.0, 0.1, {})
    stats.status({"tf_received": 0, "tf_ignored": 0})
    clock[0] = 1.0
    status = stats.status({"tf_received": 5000, "tf_ignored": 4950})
    assert status["level"] == diagnostics.WARN
    assert "/tf flood: 5000 transforms/s" in status["message"]
    assert "4950 dropped unread" in status["message"]


# ---------------------------------------------------- recovery: the same grid again
@pytest.fixture(scope="module")
def model_and_cfg():
    cfg = tiny_config(score_threshold=0.0, box_score_threshold=0.0)
    torch.manual_seed(0)
    return ODG(cfg).eval(), cfg


def tf_pipeline(model_and_cfg):
    model, cfg = model_and_cfg
    tf = TransformBuffer(max_speed=70.0, max_acceleration=30.0,
                         wanted={"base_link", *CAMS})
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0, min_interval=0.0)
    pipeline = OnlinePipeline(
        predictor, PipelineSettings.from_parameters(CAMS),
        lambda camera, frame, t: tf.lookup("base_link", frame, t, "missing_extrinsics"),
        lambda t: tf.lookup("map", "base_link", t, "pose_miss"))
    for name in CAMS:
        tf.add("base_link", name, 0.0, RIG.cameras[name].sensor2ego, static=True)
        pipeline.on_camera_info(name, scaled_K(name), *HW, frame_id=name)
    return pipeline, tf


def add_poses(tf, t0, t1):
    for t in np.arange(t0, t1, 0.02):
        tf.add("map", "base_link", float(t), pose_at(float(t)))


def process_next(pipeline):
    camera_set = pipeline.next_set(timeout=0.1)
    assert camera_set is not None
    return pipeline.process(camera_set)


def test_after_the_faults_stop_the_next_clean_set_gives_the_same_grid(model_and_cfg):
    clean, clean_tf = tf_pipeline(model_and_cfg)
    add_poses(clean_tf, 10.0, 11.5)
    for start in (10.5, 11.0):
        feed_set(clean, start, set_images(int(start * 2)))
        expected = process_next(clean)

    faulty, tf = tf_pipeline(model_and_cfg)
    add_poses(tf, 10.0, 10.7)
    feed_set(faulty, 10.5, set_images(21))
    process_next(faulty)
    faults = {
        "loop": lambda: tf.add("base_link", "map", 10.6, np.eye(4)),
        "dynamic copy": lambda: tf.add("base_link", "CAM_FRONT", 10.6,
                                       RIG.cameras["CAM_FRONT"].sensor2ego),
        "focal 1e300": lambda: faulty.on_camera_info(
            "CAM_FRONT", np.diag([1e300, 1e300, 1.0]), *HW, frame_id="CAM_FRONT"),
    }
    for name, fault in faults.items():
        try:
            fault()
        except BadInput:
            pass
    add_poses(tf, 10.7, 11.5)
    for glitch in (11.03, 11.01):            # inside the next set's stamps, 1 km / 1e300 off
        kind_of(tf.add, "map", "base_link", glitch, shifted(pose_at(glitch), 1000.0))
    # a decompression bomb in one camera of a set: skipped unread
    for name, offset, image in zip(CAMS, OFFSETS, set_images(0)):
        data = png_declaring(8000, 8000) if name == "CAM_BACK" else png(image)
        faulty.on_image(name, 10.75 + offset, EncodedImage(True, "png", data), now=10.8)
    assert kind_of(process_next, faulty) == "image_too_large"

    feed_set(faulty, 11.0, set_images(22))
    result = process_next(faulty)
    assert result.num_frames == expected.num_frames == 2
    assert (result.grid != 17).sum() > 50
    assert np.array_equal(result.grid, expected.grid)
    counters = faulty.counters()
    assert counters["image_too_large"] == 1 and counters["implausible_camera_info"] == 1


def test_odometry_glitches_are_rejected_and_counted_by_the_pipeline(model_and_cfg):
    pipeline, _ = tf_pipeline(model_and_cfg)
    for t in np.arange(10.0, 11.0, 0.02):
        pipeline.on_pose(float(t), pose_at(float(t)))
    with pytest.raises(BadInput) as error:
        pipeline.on_pose(10.99, shifted(pose_at(10.99), -1000.0))
    assert error.value.kind == "implausible_motion"
    for t in np.arange(11.0, 11.1, 0.02):                     # a teleport that stays
        kind_of(pipeline.on_pose, float(t), shifted(pose_at(float(t)), 1000.0))
    counters = pipeline.counters()
    assert counters["implausible_motion"] == 3 and counters["pose_teleports"] == 1
