"""The whole ROS-free online pipeline: messages in, prediction out; every bad input is
counted, skipped, and the pipeline goes on with the next set."""
import io
import threading
import time
import traceback

import numpy as np
import pytest
import torch
from testing.helpers import tiny_config
from PIL import Image

from odg_ros.network import ODG
from odg_ros.online.errors import BadInput
from odg_ros.online.images import EncodedImage
from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings
from odg_ros.online.predictor import OnlinePredictor
from odg_ros.online.camera_calibration import set_ego2img
from odg_ros.preprocess import adjust_intrinsics, resize_crop
from odg_ros.geometry import make_transform
from testing.online import CAMS, HW, OFFSETS, RIG, feed_set, png, scaled_K, set_images


def pose_at(t):
    """The car drives along x at 5 m/s, turning slowly."""
    yaw = 0.02 * t
    return make_transform([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)], (5.0 * t, 0.1 * t, 0.0))


@pytest.fixture(scope="module")
def model_and_cfg():
    cfg = tiny_config(score_threshold=0.0, box_score_threshold=0.0)
    torch.manual_seed(0)
    return ODG(cfg).eval(), cfg


def make_pipeline(model_and_cfg, **settings):
    model, cfg = model_and_cfg
    predictor = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)

    def extrinsics(camera, frame_id, stamp):
        if camera not in RIG.cameras:
            raise BadInput("missing_extrinsics", camera)
        return RIG.cameras[camera].sensor2ego

    return OnlinePipeline(predictor, PipelineSettings.from_parameters(CAMS, **settings),
                          extrinsics)


def feed_calibration_and_poses(pipeline, t0=10.0, t1=12.0):
    for name in CAMS:
        pipeline.on_camera_info(name, scaled_K(name), *HW, frame_id=name)
    for t in np.arange(t0, t1, 0.02):                 # 50 Hz odometry
        pipeline.on_pose(float(t), pose_at(float(t)))


def run_one(pipeline):
    camera_set = pipeline.next_set(timeout=0.1)
    assert camera_set is not None
    return pipeline.process(camera_set)


def test_pipeline_output_equals_the_predictor_on_the_same_arrays(model_and_cfg):
    model, cfg = model_and_cfg
    pipeline = make_pipeline(model_and_cfg)
    feed_calibration_and_poses(pipeline)
    reference = OnlinePredictor(model, cfg, "cpu", max_gap=1.0)
    for k in range(2):
        start = 10.5 + k / 12
        images = set_images(k)
        assert feed_set(pipeline, start, images)
        result = run_one(pipeline)
        # the same set prepared by hand: resize/crop, intrinsics, each camera at its stamp
        stamps = [start + o for o in OFFSETS]
        ego2img = set_ego2img(
            [adjust_intrinsics(scaled_K(c), HW, cfg.image_size) for c in CAMS],
            [RIG.cameras[c].sensor2ego for c in CAMS], [pose_at(t) for t in stamps],
            pose_at(start))
        expected = reference.step(np.stack([resize_crop(i, cfg.image_size) for i in images]),
                                  ego2img, pose_at(start), start)
        assert result.stamp == start and result.header == ("stamp", start)
        assert result.num_frames == k + 1
        assert (result.grid != 17).sum() > 50
        assert np.array_equal(result.grid, expected.grid)
        assert set(result.timings) == {"lookup", "decode_images", "upload", "model",
                                       "download"}
        assert 0.0 <= result.timings["lookup"] < result.timings["model"]
    assert sum(pipeline.bad_inputs.values()) == 0


def expect_skip(pipeline, kind):
    camera_set = pipeline.next_set(timeout=2.0)    # at once, or after pose_wait
    assert camera_set is not None
    with pytest.raises(BadInput) as error:
        pipeline.process(camera_set)
    assert error.value.kind == kind
    assert pipeline.bad_inputs[kind] >= 1


def test_every_bad_input_is_counted_and_the_pipeline_goes_on(model_and_cfg):
    # a set whose CameraInfo or pose has not come waits pose_wait (steady clock here)
    pipeline = make_pipeline(model_and_cfg, pose_wait=0.2)
    t = 10.0
    good = set_images(0)

    # no CameraInfo (after waiting for it)
    for t_pose in np.arange(9.0, 14.0, 0.02):
        pipeline.on_pose(float(t_pose), pose_at(float(t_pose)))
    feed_set(pipeline, t, good)
    expect_skip(pipeline, "missing_camera_info")

    # a CameraInfo with K all zero (uncalibrated) is rejected, the good one kept
    with pytest.raises(BadInput) as error:
        pipeline.on_camera_info("CAM_FRONT", np.zeros(9), *HW, frame_id="CAM_FRONT")
    assert error.value.kind == "bad_camera_info"
    for name in CAMS:
        pipeline.on_camera_info(name, scaled_K(name), *HW, frame_id=name)

    # a truncated PNG in one camera
    t += 0.25
    broken = lambda image: png(image)[:200]                          # noqa: E731
    for name, offset, image in zip(CAMS, OFFSETS, good):
        encode = broken if name == "CAM_BACK" else png
        pipeline.on_image(name, t + offset, EncodedImage(True, "png", encode(image)), now=t)
    expect_skip(pipeline, "corrupt_image")

    # a wrong image size
    t += 0.25
    small = [i[:100] for i in good]
    feed_set(pipeline, t, small)
    expect_skip(pipeline, "wrong_image_size")

    # an unsupported raw encoding
    t += 0.25
    for name, offset, image in zip(CAMS, OFFSETS, good):
        pipeline.on_image(name, t + offset, EncodedImage(False, "yuv422", image.tobytes(),
                                                         *HW, HW[1] * 2), now=t)
    expect_skip(pipeline, "unsupported_encoding")

    # NaN and non-orthonormal poses are rejected at the door
    for bad in (np.full((4, 4), np.nan), np.diag([1.0, 2.0, 1.0, 1.0])):
        with pytest.raises(BadInput) as error:
            pipeline.on_pose(t, bad)
        assert error.value.kind == "bad_pose"

    # images far beyond the last pose: pose miss
    feed_set(pipeline, 20.0, good, now=20.1)
    expect_skip(pipeline, "pose_miss")

    # a stamp from the future (clock at 5 s, image at 20.5 s): dropped before sync
    with pytest.raises(BadInput) as error:
        pipeline.on_image("CAM_FRONT", 20.5, EncodedImage(True, "png", png(good[0])), now=5.0)
    assert error.value.kind == "future_stamp"
    # a camera that is not configured
    with pytest.raises(BadInput) as error:
        pipeline.on_image("CAM_SIDE", 20.5, EncodedImage(True, "png", png(good[0])), now=21.0)
    assert error.value.kind == "unknown_camera"

    # and then a good set goes through (the bag looped back in time: sync restarts)
    feed_set(pipeline, 11.5, good, now=11.6)
    result = run_one(pipeline)
    assert result.stamp == 11.5 and (result.grid != 17).sum() > 50

    counters = pipeline.counters()
    for kind in ("missing_camera_info", "bad_camera_info", "corrupt_image", "wrong_image_size",
                 "unsupported_encoding", "bad_pose", "pose_miss", "future_stamp",
                 "unknown_camera"):
        assert counters[kind] >= 1, kind
    assert counters["bad_pose"] == 2
    assert counters["input_time_jumps"] == 1


def test_missing_extrinsics_is_a_skip(model_and_cfg):
    pipeline = make_pipeline(model_and_cfg)

    def no_tf(camera, frame_id, stamp):
        raise BadInput("missing_extrinsics", f"no transform base_link -> {frame_id}")

    pipeline.extrinsics = no_tf
    feed_calibration_and_poses(pipeline)
    feed_set(pipeline, 10.5, set_images(0))
    expect_skip(pipeline, "missing_extrinsics")


def test_slow_worker_drops_stale_sets(model_and_cfg):
    pipeline = make_pipeline(model_and_cfg)
    feed_calibration_and_poses(pipeline)
    for k in range(5):                                 # five sets arrive, nobody processes
        feed_set(pipeline, 10.2 + k / 12, set_images(k))
    result = run_one(pipeline)                          # the worker wakes up: the newest set
    assert result.stamp == pytest.approx(10.2 + 4 / 12)
    assert pipeline.counters()["stale_sets_dropped"] == 4
    assert pipeline.next_set(timeout=0.01) is None


def jpeg(array):
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="JPEG", quality=90)
    return buffer.getvalue()


def decoding_ahead(model_and_cfg):
    """A pipeline decoding in its own thread; its model blocks on ``release`` in its first
    step, and ``prepared`` records the stamp of every set decoded (an event each)."""
    pipeline = make_pipeline(model_and_cfg)
    feed_calibration_and_poses(pipeline)
    prepared, bad, errors = {}, [], []
    prepare = pipeline.prepare

    def recording_prepare(camera_set):
        result = prepare(camera_set)
        prepared.setdefault(camera_set.reference_stamp, threading.Event()).set()
        return result

    pipeline.prepare = recording_prepare
    pipeline.start_decoding(bad.append, lambda: errors.append(traceback.format_exc()))
    return pipeline, prepared, bad, errors


def wait_prepared(prepared, stamp, timeout=10.0):
    deadline = time.monotonic() + timeout
    while stamp not in prepared and time.monotonic() < deadline:
        time.sleep(0.005)
    return prepared.setdefault(stamp, threading.Event()).wait(max(0.0, deadline
                                                                 - time.monotonic()))


def infer_in_thread(pipeline, prepared_set):
    out = {}
    thread = threading.Thread(target=lambda: out.setdefault("result",
                                                            pipeline.infer(prepared_set)))
    thread.start()
    return thread, out


def test_the_next_set_decodes_while_the_model_runs(model_and_cfg):
    pipeline, prepared, bad, errors = decoding_ahead(model_and_cfg)
    a, b = 10.5, 10.5 + 1 / 12
    step = pipeline.predictor.step
    seen = {}

    def slow_step(*args):      # the model of set a lasts until set b is decoded (or 10 s)
        if not seen:
            seen["b decoded during the model of a"] = wait_prepared(prepared, b)
        return step(*args)

    pipeline.predictor.step = slow_step
    try:
        feed_set(pipeline, a, set_images(0), encode=jpeg)
        set_a = pipeline.next_prepared(timeout=10.0)
        assert set_a is not None and set_a.camera_set.reference_stamp == a
        thread, out = infer_in_thread(pipeline, set_a)
        feed_set(pipeline, b, set_images(1), encode=jpeg)
        thread.join(30.0)
        assert seen == {"b decoded during the model of a": True}
        assert out["result"].stamp == a
        set_b = pipeline.next_prepared(timeout=10.0)
        assert pipeline.infer(set_b).stamp == b
        assert set(out["result"].timings) == {"lookup", "decode_images", "upload", "model",
                                              "download"}
        assert not bad and not errors
    finally:
        pipeline.close()
    assert not pipeline._decoding.is_alive()


def test_decoding_ahead_keeps_the_newest_set_in_order_and_skips_bad_sets(model_and_cfg):
    pipeline, prepared, bad, errors = decoding_ahead(model_and_cfg)
    release = threading.Event()
    step = pipeline.predictor.step
    pipeline.predictor.step = lambda *args: (release.wait(10.0), step(*args))[1]
    stamps = [10.5 + k / 12 for k in range(4)]           # a, b (corrupt), c, d
    try:
        feed_set(pipeline, stamps[0], set_images(0), encode=jpeg)
        thread, out = infer_in_thread(pipeline, pipeline.next_prepared(timeout=10.0))
        # while the model runs on a: a corrupt set is a counted skip, reported at once
        feed_set(pipeline, stamps[1], set_images(1),
                 encode=lambda image: jpeg(image)[:300])
        deadline = time.monotonic() + 10.0
        while not bad and time.monotonic() < deadline:
            time.sleep(0.005)
        assert [error.kind for error in bad] == ["corrupt_image"]
        assert pipeline.counters()["corrupt_image"] == 1
        # c is decoded, then d replaces it: the model's next set is the newest
        feed_set(pipeline, stamps[2], set_images(2), encode=jpeg)
        assert wait_prepared(prepared, stamps[2])
        feed_set(pipeline, stamps[3], set_images(3), encode=jpeg)
        assert wait_prepared(prepared, stamps[3])
        release.set()
        thread.join(30.0)
        assert out["result"].stamp == stamps[0]
        following = pipeline.next_prepared(timeout=1.0)
        assert following.camera_set.reference_stamp == stamps[3]
        assert pipeline.next_prepared(timeout=0.05) is None
        assert pipeline.infer(following).num_frames == 2
        assert pipeline.counters()["stale_sets_dropped"] == 1
        assert not errors
    finally:
        release.set()
        pipeline.close()


def test_the_result_carries_what_the_whole_camera_images_see(model_and_cfg):
    """The pipeline passes each camera's whole image (CameraInfo's size) to the visibility:
    its result equals the predictor's given those bounds, not the network input's crop."""
    from odg_ros.network.visibility import image_bounds
    model, cfg = model_and_cfg
    pipeline = make_pipeline(model_and_cfg)
    feed_calibration_and_poses(pipeline)
    start, images = 10.5, set_images(0)
    assert feed_set(pipeline, start, images)
    result = run_one(pipeline)
    ego2img = set_ego2img([adjust_intrinsics(scaled_K(c), HW, cfg.image_size) for c in CAMS],
                          [RIG.cameras[c].sensor2ego for c in CAMS],
                          [pose_at(start + o) for o in OFFSETS], pose_at(start))
    inputs = np.stack([resize_crop(i, cfg.image_size) for i in images])
    whole = OnlinePredictor(model, cfg, "cpu").step(
        inputs, ego2img, pose_at(start), start, image_bounds([HW] * 6, cfg.image_size))
    cropped = OnlinePredictor(model, cfg, "cpu").step(inputs, ego2img, pose_at(start), start)
    assert result.observed.shape == result.grid.shape and result.observed.any()
    assert np.array_equal(result.observed, whole.observed)
    assert result.observed.sum() > cropped.observed.sum()     # the cropped rows count


def test_pacing_decodes_the_next_set_when_the_model_is_due_to_want_it():
    """DecodePacing's clock arithmetic: unknown durations -> decode at once; then just
    before the current set is due to end, less one decode; one set waiting -> after the
    next take."""
    from odg_ros.online.pacing import MARGIN_S, DecodePacing
    now = [100.0]
    pacing = DecodePacing(clock=lambda: now[0])
    assert pacing.due() is None
    pacing.decoded(0.02)
    pacing.taken()                                   # the first set: 0.5 s of model
    assert pacing.due() is None                      # its duration is not known yet
    now[0] = 100.5
    pacing.ready()
    pacing.ready()                                   # a second ask measures nothing
    assert pacing.busy_s == pytest.approx(0.5)
    pacing.taken()
    assert pacing.due() == pytest.approx(100.5 + 0.5 - 0.02 - MARGIN_S)
    pacing.decoded(0.02)
    assert pacing.due() == float("inf")              # one set waits for the next take
    now[0] = 101.0
    pacing.ready()
    pacing.taken()
    assert pacing.due() == pytest.approx(101.0 + 0.5 - 0.02 - MARGIN_S)


def test_a_node_slower_than_its_cameras_decodes_one_fresh_set_per_output(model_and_cfg):
    """Sets every 50 ms, a model of at least 300 ms: once the durations are known (from the
    third output on), the decoding thread decodes about one set per output, not six or
    more, and the set each output starts on is among the newest that had arrived."""
    pipeline, prepared, bad, errors = decoding_ahead(model_and_cfg)
    feed_calibration_and_poses(pipeline, 10.0, 40.0)
    step = pipeline.predictor.step
    pipeline.predictor.step = lambda *args: (time.sleep(0.3), step(*args))[1]
    fed, outputs, stop = [], [], threading.Event()

    def feed():
        for k in range(300):
            if stop.is_set():
                return
            fed.append(10.5 + k / 12)
            feed_set(pipeline, fed[-1], set_images(k % 3), encode=jpeg)
            time.sleep(0.05)

    def work():
        while not stop.is_set() and len(outputs) < 7:
            prepared_set = pipeline.next_prepared(timeout=0.2)
            if prepared_set is not None:         # (decodes so far, sets behind the newest)
                age = round((fed[-1] - prepared_set.camera_set.reference_stamp) * 12)
                outputs.append((len(prepared), age))
                pipeline.infer(prepared_set)

    feeder, worker = threading.Thread(target=feed), threading.Thread(target=work)
    try:
        feeder.start(), worker.start()
        worker.join(60.0)
    finally:
        stop.set()
        feeder.join(10.0)
        pipeline.close()
    assert len(outputs) == 7 and not bad and not errors, outputs
    decodes = outputs[-1][0] - outputs[3][0]             # from the 4th to the 7th output
    assert decodes <= 1.5 * 3, f"{decodes} sets decoded for 3 outputs: {outputs}"
    assert max(age for _, age in outputs[3:]) <= 2, outputs       # a set or two behind
