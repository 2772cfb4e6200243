"""odg_node end to end with real rclpy: the node runs in its own process (started like the
console script, with a params file), this test publishes cameras / CameraInfo / poses and
listens to the outputs.

* the published grid equals the offline model's output on the same frames (exact labels);
* parameters from the YAML file are applied (namespace, output frame, thresholds...);
* every bad input gives a diagnostic counter and the node keeps running;
* a model slower than the cameras drops stale sets (latest wins) instead of queueing them;
* TF as pose and extrinsics source;
* unknown space in the grid, the BEV and the cloud (and none with visibility false), the
  debug timing topics, per-topic input diagnostics on a steady timer, silent topics named.
"""
from __future__ import annotations

import itertools
import signal
import time

import numpy as np
import pytest
import torch

from odg_ros.geometry import ego_warp
from odg_ros.online.camera_calibration import set_ego2img
from odg_ros.preprocess import adjust_intrinsics, normalize, resize_crop
from testing.node_harness import (FAST, NODE, Harness, checkpoint, jpeg,  # noqa: F401
                                  pose_at, start_node, tf_transform)
from testing.online import CAMS, HW, OFFSETS, RIG, png, scaled_K, set_images


def offline_grids(checkpoint, sets, t0):
    """The model run offline (every frame's features recomputed) on the same frames."""
    from odg_ros.network.checkpoint import load_model
    from odg_ros.network.padding import pad_occupancy
    from odg_ros.network.postprocess import box_list, occupancy_grid
    model, cfg = load_model(checkpoint, device="cpu", score_threshold=0.0,
                            box_score_threshold=0.0)
    K = [adjust_intrinsics(scaled_K(c), HW, cfg.image_size) for c in CAMS]
    sensor2ego = [RIG.cameras[c].sensor2ego for c in CAMS]
    frames = []
    for start, images in sets:
        poses = [pose_at(start + o, t0) for o in OFFSETS]
        frames.append(dict(images=np.stack([resize_crop(i, cfg.image_size) for i in images]),
                           ego2img=set_ego2img(K, sensor2ego, poses, poses[0]),
                           pose=poses[0], stamp=start))
    grids = []
    for i in range(len(frames)):
        chosen = frames[i::-1][:cfg.num_frames]
        with torch.inference_mode():
            out = model(torch.stack([normalize(torch.from_numpy(f["images"]))
                                     for f in chosen])[None],
                        torch.tensor(np.stack([f["ego2img"] for f in chosen]),
                                     dtype=torch.float32)[None],
                        torch.tensor(np.stack([ego_warp(chosen[0]["pose"], f["pose"])
                                               for f in chosen]), dtype=torch.float32)[None],
                        torch.tensor([chosen[0]["stamp"] - f["stamp"] for f in chosen],
                                     dtype=torch.float32)[None])
        grid, confidence = occupancy_grid(out, cfg)
        if cfg.occupancy_padding:       # the node publishes the padded grid, as evaluated
            grid, confidence = pad_occupancy(grid, confidence, cfg.num_classes,
                                             cfg.score_threshold)
        grids.append((grid[0].numpy(), len(box_list(out, cfg)[0])))
    return grids


def test_node_output_equals_offline_model_and_yaml_parameters_apply(
        ros_context, rclpy_module, checkpoint, start_node):
    child, params, log = start_node(checkpoint, slop=0.06, history_frames=3)
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)

    values = h.get_parameters(["slop", "history_frames", "score_threshold", "output_frame",
                               "image_topic", "camera_names"])
    assert values == {"slop": 0.06, "history_frames": 3, "score_threshold": 0.0,
                      "output_frame": "ego_test", "image_topic": "/test/{camera}/image",
                      "camera_names": list(CAMS)}

    t0 = time.time() - 5.0                         # stamps a bit in the past: not "future"
    h.publish_infos()
    h.publish_poses(t0 - 0.5, t0 + 2.0, t0)
    sets = [(t0 + 0.2 + 0.5 * k, set_images(k)) for k in range(3)]
    for k, (start, images) in enumerate(sets):
        h.publish_set(start, images)
        assert h.spin_until(lambda: len(h.received["grid"]) > k, 60, child, log), \
            f"no grid for set {k}; diagnostics {h.counters()[0]}"
    expected = offline_grids(checkpoint, sets, t0)

    for k, (msg, (grid, num_boxes)) in enumerate(zip(h.received["grid"], expected)):
        labels = np.frombuffer(bytes(msg.labels), np.uint8).reshape(msg.size_x, msg.size_y,
                                                                     msg.size_z)
        assert (labels != 17).sum() > 50                      # a real comparison
        assert np.array_equal(labels, grid), f"set {k}: {(labels != grid).sum()} voxels differ"
        assert msg.header.frame_id == "ego_test"
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        assert stamp == pytest.approx(sets[k][0], abs=1e-6)   # CAM_FRONT's stamp
        assert len(msg.confidence) == labels.size and msg.memory_order == "xyz_c"

    # the other outputs of the last set agree with the grid; they arrive after it (depth-1
    # latest-wins publishers), so wait for the last set's stamp on each, not for any message
    last_stamp = h.received["grid"][-1].header.stamp

    def has_last_set(topic):
        if not h.received[topic]:
            return False
        newest = h.received[topic][-1]
        header = newest.markers[0].header if topic == "markers" else newest.header  # DELETEALL
        return header.stamp == last_stamp

    assert h.spin_until(lambda: all(map(has_last_set, ("objects", "cloud", "bev", "markers"))),
                        30), "the last set's cloud, bev, objects and markers did not all arrive"
    last = np.frombuffer(bytes(h.received["grid"][-1].labels), np.uint8)
    assert h.received["cloud"][-1].width == int((last != 17).sum())
    assert len(h.received["objects"][-1].objects) == expected[-1][1]
    bev = h.received["bev"][-1]
    assert (bev.info.width, bev.info.height) == (200, 200) and len(bev.data) == 40000
    h.spin_until(lambda: False, 0.5)
    counters, status = h.counters()
    assert status is not None and counters["outputs"] == "3"
    assert all(counters[k] == "0" for k in ("corrupt_image", "pose_miss", "missing_camera_info",
                                            "internal_errors"))
    assert child.poll() is None


def test_bad_inputs_are_skipped_with_diagnostics_and_the_node_keeps_running(
        ros_context, rclpy_module, checkpoint, start_node):
    child, params, log = start_node(checkpoint, precision="bf16")   # the bf16 path end to end
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)
    t0 = time.time() - 60.0
    good = set_images(0)
    h.publish_poses(t0 - 0.5, t0 + 6.0, t0, rate=10.0)

    def expect(kind, timeout=30):
        assert h.spin_until(lambda: int(h.counters()[0].get(kind, "0")) >= 1, timeout,
                            child, log), f"no {kind} in diagnostics: {h.counters()[0]}"

    h.publish_set(t0 + 0.2, good)                                  # no CameraInfo yet
    expect("missing_camera_info")
    h.publish_infos(K_of=lambda c: np.zeros((3, 3)))               # uncalibrated
    expect("bad_camera_info")
    h.publish_infos()
    # odometry is best effort: poses sent before the node's subscription matched may be lost
    # (then the next set is a pose miss, not the bad input under test). The node provably
    # listens now; the same stamps again replace rather than add.
    h.publish_poses(t0 - 0.5, t0 + 6.0, t0, rate=10.0)
    h.spin_until(lambda: False, 0.3)
    h.publish_set(t0 + 0.7, good, encode=lambda i: jpeg(i)[:300], fmt="jpeg")   # truncated
    expect("corrupt_image")
    h.publish_set(t0 + 1.2, [i[:100] for i in good])                # wrong size
    expect("wrong_image_size")
    h.publish_set(t0 + 1.7, good, fmt="16UC1; compressedDepth")     # not a colour image
    expect("unsupported_encoding")
    h.publish_pose(t0 + 1.8, np.full((4, 4), np.nan), (1.0, 0.0, 0.0, 0.0))   # NaN position
    expect("bad_pose")
    h.publish_set(t0 + 30.0, good)                                  # no pose there
    expect("pose_miss")
    h.publish_set(time.time() + 60.0, good)                         # from the future
    expect("future_stamp")
    h.publish_poses(t0 + 30.0, t0 + 32.0, t0, rate=20.0)
    assert not h.received["grid"]
    h.publish_set(t0 + 31.0, good)                                  # and a good one
    assert h.spin_until(lambda: len(h.received["grid"]) == 1, 60, child, log)
    _, status = h.counters()
    assert status is not None
    assert child.poll() is None
    log.seek(0)
    text = log.read()
    for kind in ("corrupt_image", "wrong_image_size", "pose_miss", "missing_camera_info"):
        assert f"odg_node.{kind}]" in text, f"no warning for {kind}:\n{text}"
    assert "precision bf16" in text
    assert "Traceback" not in text


def test_latest_wins_under_a_slow_model_with_tf_sources(
        ros_context, rclpy_module, checkpoint, start_node):
    # The CPU preset with random weights (checkpoint random) is
    # far slower on a CPU than sets arriving every 42 ms of wall time (stamps 1/12 s apart),
    # so the worker must skip sets rather than queue them.
    child, params, log = start_node("random", preset="odg_cpu", pose_source="tf",
                                    extrinsics_source="tf")
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)

    def transform(parent, child_frame, t, T):
        return tf_transform(h, parent, child_frame, t, T)

    t0 = time.time() - 10.0
    h.tf_static.publish(h.classes["TFMessage"](transforms=[
        transform("base_link", c, t0, RIG.cameras[c].sensor2ego) for c in CAMS]))
    for t in np.arange(t0 - 0.5, t0 + 3.0, 0.02):
        h.tf.publish(h.classes["TFMessage"](transforms=[transform("map", "base_link", float(t),
                                                                  pose_at(float(t), t0))]))
        h.executor.spin_once(timeout_sec=0.001)
    h.publish_infos()
    h.spin_until(lambda: False, 0.3)
    num_sets = 24                                   # 2 s of 12 Hz camera stamps
    starts = [t0 + 0.2 + k / 12 for k in range(num_sets)]
    for k, start in enumerate(starts):
        h.publish_set(start, set_images(k))
        h.spin_until(lambda: False, 1 / 24)
    last = starts[-1]
    assert h.spin_until(lambda: h.received["grid"] and abs(
        h.received["grid"][-1].header.stamp.sec + h.received["grid"][-1].header.stamp.nanosec
        * 1e-9 - last) < 1e-6, 60, child, log), "the newest set was never processed"
    h.spin_until(lambda: False, 0.5)
    counters, _ = h.counters()
    outputs = len(h.received["grid"])
    assert outputs < num_sets
    assert int(counters["stale_sets_dropped"]) >= 1
    assert int(counters["dropped_incomplete_sets"]) == 0
    assert int(counters["pose_miss"]) == 0 and int(counters["missing_extrinsics"]) == 0
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in h.received["grid"]]
    assert stamps == sorted(stamps)
    log.seek(0)
    assert "RANDOM WEIGHTS" in log.read()           # asked for by name, still a loud warning
    print(f"{num_sets} sets published at 24 Hz, {outputs} processed, "
          f"{counters['stale_sets_dropped']} stale sets dropped")


def test_signals_during_inference_and_shutdown_exit_cleanly(
        ros_context, rclpy_module, start_node):
    # Ctrl-C, then a supervisor's stop 0.3 s later, while the (slow, random-weight) CPU
    # preset is inside a step, then more of both until the process is gone (one landing in
    # the interpreter's own teardown, where Python has put back the default handlers, used
    # to kill it with -15): a clean shutdown and exit status 0.
    child, params, log = start_node("random", preset="odg_cpu")
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)
    t0 = time.time() - 5.0
    h.publish_infos()
    h.publish_poses(t0 - 0.5, t0 + 1.0, t0)
    h.spin_until(lambda: False, 0.3)
    h.publish_set(t0 + 0.2, set_images(0))
    assert h.spin_until(lambda: int(h.counters()[0].get("sets_completed", "0")) >= 1, 30,
                        child, log), f"the set never completed: {h.counters()[0]}"
    assert not h.received["grid"], "inference ended before the signals: nothing tested"
    child.send_signal(signal.SIGINT)
    time.sleep(0.3)
    child.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 30
    for k in itertools.count():
        if child.poll() is not None or time.monotonic() > deadline:
            break
        child.send_signal((signal.SIGINT, signal.SIGTERM)[k % 2])
        time.sleep(0.01)
    returncode = child.wait(timeout=5)
    log.seek(0)
    text = log.read()
    assert returncode == 0, f"exit status {returncode}:\n{text}"
    assert "Traceback" not in text


def test_hostile_tf_and_bad_calibration_never_stop_the_node(
        ros_context, rclpy_module, checkpoint, start_node):
    """A TF loop, a stray dynamic copy of a static camera link, a busy tree of unneeded
    frames, a CameraInfo with fx = fy = 1e300 and an image stamp with nanosec >= 1e9, all
    between two clean sets: each is rejected and counted, and the next clean set gives the
    grid of the offline model (as if no fault had happened). Then a /tf flood: sets still
    give grids, the flood shows in diagnostics, RSS stays within 150 MB."""
    child, params, log = start_node(checkpoint, pose_source="tf", extrinsics_source="tf")
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)
    TFMessage = h.classes["TFMessage"]
    t0 = time.time() - 10.0
    h.tf_static.publish(TFMessage(transforms=[
        tf_transform(h, "base_link", c, t0, RIG.cameras[c].sensor2ego) for c in CAMS]))

    def publish_poses(t_from, t_to):
        for t in np.arange(t_from, t_to, 0.02):
            h.tf.publish(TFMessage(transforms=[tf_transform(h, "map", "base_link", float(t),
                                                            pose_at(float(t), t0))]))
            h.executor.spin_once(timeout_sec=0.001)

    publish_poses(t0 - 0.5, t0 + 0.5)
    h.publish_infos()
    h.spin_until(lambda: False, 0.3)
    sets = [(t0 + 0.2, set_images(0)), (t0 + 0.7, set_images(1))]
    h.publish_set(*sets[0])
    assert h.spin_until(lambda: len(h.received["grid"]) == 1, 60, child, log), \
        f"no grid for the clean set: {h.counters()[0]}"

    steady_rss, steady_peak = rss_mb(child.pid), rss_mb(child.pid, "VmHWM")

    # the faults
    h.tf.publish(TFMessage(transforms=[tf_transform(h, "base_link", "map", t0 + 0.4,
                                                    np.eye(4))]))
    h.tf.publish(TFMessage(transforms=[tf_transform(h, "base_link", "CAM_FRONT", t0 + 0.4,
                                                    RIG.cameras["CAM_FRONT"].sensor2ego)]))
    busy = TFMessage(transforms=[tf_transform(h, "world", f"fixed_{k}", t0, np.eye(4))
                                 for k in range(250)])
    for _ in range(4):
        h.tf.publish(busy)
    h.publish_infos(K_of=lambda c: np.diag([1e300, 1e300, 1.0]))
    h.spin_until(lambda: False, 0.3)
    h.publish_infos()
    # a decompression bomb in one camera of a set: 8000 x 8000 px in 62 kB of PNG
    bomb = png(np.zeros((8000, 8000), np.uint8))
    images = set_images(0)
    h.publish_set(t0 + 0.45, images,
                  encode=lambda image: bomb if image is images[3] else png(image))
    bad = h.classes["CompressedImage"](format="png", data=png(set_images(0)[0]))
    bad.header.stamp.sec, bad.header.stamp.nanosec = int(t0) + 1, 1_500_000_000
    h.images["CAM_FRONT"].publish(bad)
    publish_poses(t0 + 0.5, t0 + 1.0)

    def counted(kinds):
        counters = h.counters()[0]
        return all(int(counters.get(k, "0")) >= n for k, n in kinds.items())

    faults = {"bad_tf": 1, "implausible_camera_info": 6, "bad_stamp": 1, "tf_ignored": 1000,
              "image_too_large": 1}
    assert h.spin_until(lambda: counted(faults), 30, child, log), \
        f"faults not all counted: {h.counters()[0]}"
    h.publish_set(*sets[1])
    assert h.spin_until(lambda: len(h.received["grid"]) == 2, 60, child, log), \
        f"no grid after the faults: {h.counters()[0]}"
    for msg, (grid, _) in zip(h.received["grid"], offline_grids(checkpoint, sets, t0)):
        labels = np.frombuffer(bytes(msg.labels), np.uint8).reshape(grid.shape)
        assert (labels != 17).sum() > 50
        assert np.array_equal(labels, grid), f"{(labels != grid).sum()} voxels differ"
    counters = h.counters()[0]
    assert counters["missing_extrinsics"] == "0" and counters["pose_miss"] == "0"

    # A busy tree: 250 fixed frames at 20 Hz (5,000 transforms/s) with sets at 2 Hz. It used
    # to starve the executor (0 grids for 16 sets on the loaded 2-core machine).
    busy = TFMessage(transforms=[tf_transform(h, "world", f"fixed_{k}", t0, np.eye(4))
                                 for k in range(250)])
    start = time.time()
    grids_before, sets_in_flood, next_set = len(h.received["grid"]), 0, start + 1.0
    while time.time() < start + 4.0:
        now = time.time()
        h.tf.publish(busy)
        for dt in (-0.04, -0.02, 0.0):
            h.tf.publish(TFMessage(transforms=[tf_transform(h, "map", "base_link", now + dt,
                                                            pose_at(now + dt, t0))]))
        if now >= next_set:
            h.publish_set(now - 0.142, set_images(sets_in_flood))
            sets_in_flood, next_set = sets_in_flood + 1, next_set + 0.5
        h.spin_until(lambda: False, max(0.0, 0.05 - (time.time() - now)))
    h.spin_until(lambda: len(h.received["grid"]) - grids_before >= sets_in_flood - 1, 10)
    grids_in_flood = len(h.received["grid"]) - grids_before
    # (fewer grids than sets: a loaded CPU is slower than 2 Hz, stale sets are dropped)
    assert grids_in_flood >= 2, (grids_in_flood, sets_in_flood)
    assert any("/tf flood" in status.message for array in h.received["diagnostics"]
               for status in array.status), "the flood never showed in diagnostics"
    assert rss_mb(child.pid) < steady_rss + 150, (steady_rss, rss_mb(child.pid))
    assert rss_mb(child.pid, "VmHWM") < steady_peak + 150, (steady_peak,
                                                            rss_mb(child.pid, "VmHWM"))
    print(f"node RSS {steady_rss:.0f} MB (peak {steady_peak:.0f}) after the clean set, "
          f"{rss_mb(child.pid):.0f} MB (peak {rss_mb(child.pid, 'VmHWM'):.0f}) after the "
          f"faults and a /tf flood; {grids_in_flood} grids for {sets_in_flood} sets during "
          "the flood")
    assert child.poll() is None
    log.seek(0)
    assert "Traceback" not in log.read()


def rss_mb(pid, field="VmRSS"):
    """Resident memory of a process (VmHWM: its peak), MB."""
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(field)) / 1024


# ------------------------------------------- unknown space, timing in the right clock, inputs
# Unknown space in every output, the debug timing topics, per-topic input diagnostics on a
# steady timer ("no input for N s" once the inputs stop, even on a sim clock that never
# ticks), and the no-output ERROR naming the topics that never sent.


def latest_status(h):
    """(counters, status) of the newest diagnostics, ({}, None) before any."""
    return h.counters()


def message(h) -> str:
    status = latest_status(h)[1]
    return "" if status is None else status.message


def test_unknown_space_timing_and_inputs(ros_context, rclpy_module, checkpoint, start_node):
    from std_msgs.msg import Float64
    child, params, log = start_node(checkpoint, **FAST)
    h = Harness(rclpy_module, ros_context)
    debug = {"processing": [], "latency": []}
    subscriptions = [h.node.create_subscription(Float64, f"{NODE}/debug/{topic}",
                                                lambda m, k=key: debug[k].append(m.data), 10)
                     for key, topic in (("processing", "processing_time_ms"),
                                        ("latency", "pipeline_latency_ms"))]
    h.wait_for_node(child, log)
    assert h.spin_until(lambda: all(s.get_publisher_count() > 0 for s in subscriptions), 30,
                        child, log)
    assert h.feed_until(lambda: h.received["grid"] and h.received["bev"] and
                        h.received["cloud"] and debug["latency"], time.time() - 5.0,
                        child, log), message(h)
    grid = h.received["grid"][-1]
    observed = np.frombuffer(bytes(grid.observed), np.uint8)
    assert observed.size == len(grid.labels) and set(np.unique(observed)) == {0, 1}
    bev = np.frombuffer(bytes(h.received["bev"][-1].data), np.int8)
    assert (bev == -1).sum() > 1000 and (bev == 0).sum() > 1000      # unknown is not free
    assert "observed" in [f.name for f in h.received["cloud"][-1].fields]
    assert debug["processing"][-1] > 0
    assert debug["latency"][-1] > 4000            # the stamps are ~5 s old on the node clock
    counters, status = latest_status(h)
    assert int(counters["/test/CAM_FRONT/image: received"]) >= 1
    assert int(counters["/test/odom: received"]) >= 10
    # the inputs stop: within no_output_timeout the diagnostics say so
    assert h.spin_until(lambda: "no input for" in message(h), 10, child, log), message(h)
    # counted on (rounded to 0.1 s): more than the timeout once the next report comes
    assert h.spin_until(lambda: float(latest_status(h)[0]["/test/odom: seconds since last"])
                        > 1.0, 10, child, log), latest_status(h)[0]


def test_no_output_names_the_topics_that_never_sent(ros_context, rclpy_module, checkpoint,
                                                    start_node):
    """A wrong image topic pattern: the camera infos and poses arrive, no image ever. The
    node waits for its first set (WARN, never ERROR: nothing failed yet) and names the
    topics it waits for, and only those (not the optional /tf and /tf_static)."""
    child, params, log = start_node(checkpoint, image_topic="/wrong/{camera}/image", **FAST)
    h = Harness(rclpy_module, ros_context)
    h.spin_until(lambda: h.node.count_subscribers(f"/wrong/{CAMS[0]}/image") > 0, 60,
                 child, log)

    def named():
        status = latest_status(h)[1]
        return status is not None and "never received" in status.message \
            and int(latest_status(h)[0]["/test/odom: received"]) > 0

    start = time.monotonic()
    while time.monotonic() - start < 30 and not (named() and time.monotonic() - start > 3):
        h.publish_infos()
        h.publish_pose(time.time(), np.eye(4))
        h.spin_until(lambda: False, 0.1)
    status = latest_status(h)[1]
    assert named(), status.message
    assert status.message == "waiting for the first complete camera set; never received: " \
        + ", ".join(f"/wrong/{c}/image" for c in CAMS)
    levels = {s.level for array in h.received["diagnostics"] for s in array.status
              if "odg_node" in s.name}
    assert levels == {b"\x01"}, levels            # WARN throughout, 3 s (3 x the timeout)


def test_diagnostics_run_on_a_steady_timer_under_sim_time(ros_context, rclpy_module,
                                                          checkpoint, start_node):
    """use_sim_time with no /clock at all: a timer on the node's clock would never fire."""
    child, params, log = start_node(checkpoint, use_sim_time=True, **FAST)
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)
    assert h.spin_until(lambda: len(h.received["diagnostics"]) >= 3, 20, child, log)
    stamps = [a.header.stamp.sec + a.header.stamp.nanosec * 1e-9
              for a in h.received["diagnostics"]]
    assert max(stamps) == 0.0                     # stamped in sim time, which stands still


def test_visibility_false_turns_it_off(ros_context, rclpy_module, checkpoint, start_node):
    child, params, log = start_node(checkpoint, visibility=False, **FAST)
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)
    assert h.feed_until(lambda: h.received["grid"] and h.received["bev"], time.time() - 5.0,
                        child, log), message(h)
    assert len(h.received["grid"][-1].observed) == 0
    assert -1 not in set(h.received["bev"][-1].data)
