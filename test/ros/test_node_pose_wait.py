"""odg_node with real rclpy fed the way public nuScenes converters write their bags, played in
real time in log-time order:

* /tf only at 2 Hz keyframes, all dynamic (map -> base_link and base_link -> every camera,
  no /tf_static), with gaps of 0.55 and 0.75 s, under use_sim_time with /clock published
  before each message (as ``odg replay --clock`` does); the node started 6.5 s before the
  first message, longer than no_output_timeout and pose_wait together;
* odometry at 50 Hz written in bursts every 0.5 s, up to 0.5 s after the stamps it carries,
  and no TF at all (extrinsics auto: the rig file).

Either way: 0 pose_miss, every completed set published or dropped as stale, each camera's
extrinsics source in /diagnostics, no ERROR before the first output and /tf_static never
named as missing.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from testing.node_harness import (FAST, Harness, checkpoint, jpeg, pose_at,  # noqa: F401
                                  start_node, tf_transform)
from testing.online import CAMS, HW, OFFSETS, RIG, scaled_K, set_images

KEYFRAME_GAPS = (0.5, 0.55, 0.5, 0.75, 0.5, 0.5, 0.5)    # 3.8 s
# fast diagnostics; the default no-output timeout, which the tiny model's first set (seconds
# to infer on a loaded machine, after up to pose_wait of waiting) stays within
SLOW_MODEL = dict(FAST, no_output_timeout=5.0)
ERROR = b"\x02"


class Player:
    """Publishes (log time, action) events at their log times, /clock first when
    ``sim_time`` (the first event ``lead`` s after ``play``), else at the wall time equal to
    the log time; spins the harness in between."""

    def __init__(self, h: Harness, start: float, sim_time: bool):
        self.h, self.start, self.sim_time = h, start, sim_time
        self.events = []
        if sim_time:
            from rosgraph_msgs.msg import Clock
            self.clock = h.node.create_publisher(Clock, "/clock", 10)
            self.Clock = Clock

    def at(self, log_time, action):
        self.events.append((log_time, len(self.events), action))

    def play(self, lead=0.3):
        wall0 = time.monotonic() + (lead if self.sim_time else self.start - time.time())
        for log_time, _, action in sorted(self.events):
            delay = wall0 + (log_time - self.start) - time.monotonic()
            if delay > 0:
                self.h.spin_until(lambda: False, delay)
            if self.sim_time:
                self.clock.publish(self.Clock(clock=self.h.stamp(log_time)))
            action()
            self.h.executor.spin_once(timeout_sec=0)

    def cameras(self, start, stop, encoded):
        """Sets every 1/12 s, each camera's image (and CameraInfo, as the converter writes
        one with every image) at its own stamp."""
        for m in range(int(round((stop - start) * 12)) + 1):
            for c, offset in zip(CAMS, OFFSETS):
                t = start + m / 12 + offset
                self.at(t, lambda t=t, c=c, data=encoded[m % len(encoded)][c]:
                        self.publish_image(c, t, data))

    def publish_image(self, camera, t, data):
        msg = self.h.classes["CompressedImage"](format="jpeg", data=data)
        msg.header.stamp = self.h.stamp(t)
        msg.header.frame_id = camera
        self.h.images[camera].publish(msg)
        info = self.h.classes["CameraInfo"]()
        info.header.stamp, info.header.frame_id = msg.header.stamp, camera
        info.height, info.width = HW
        info.k = [float(v) for v in np.asarray(scaled_K(camera)).ravel()]
        self.h.infos[camera].publish(info)


def encoded_sets():
    return [{c: jpeg(image) for c, image in zip(CAMS, set_images(seed))} for seed in range(3)]


# Where a completed set can end: published, dropped as stale, or refused under one of these
# names (a set's look-ups, its decoding, its images).
SET_REFUSALS = ("pose_miss", "missing_extrinsics", "missing_camera_info", "bad_pose",
                "corrupt_image", "unsupported_encoding", "wrong_image_size", "image_too_large")


def unaccounted(counters) -> int | None:
    """Completed sets neither published, nor dropped as stale, nor refused: waiting, being
    decoded or in the model (None before the first report)."""
    if not counters:
        return None
    n = {k: int(v) for k, v in counters.items() if v.lstrip("-").isdigit()}
    return n["sets_completed"] - n["outputs"] - n["stale_sets_dropped"] - \
        sum(n[k] for k in SET_REFUSALS)


def settled(h):
    """Every completed set is accounted for: published, dropped as stale or refused."""
    counters = h.counters()[0]
    return bool(counters) and int(counters["sets_completed"]) > 0 and \
        unaccounted(counters) == 0 and counters["sets_waiting"] == "0"


def check_the_run(h, child, log, source):
    if not h.spin_until(lambda: settled(h), 90, child, log):
        log.seek(0)
        raise AssertionError(f"sets not accounted for after 90 s: {h.counters()[0]}\n"
                             f"{log.read()[-3000:]}")
    h.spin_until(lambda: False, 0.5)
    counters, status = h.counters()
    n = {k: int(v) for k, v in counters.items() if v.lstrip("-").isdigit()}
    print({k: n[k] for k in ("sets_completed", "outputs", "stale_sets_dropped", "sets_waited",
                             "pose_miss", "dropped_incomplete_sets")})
    assert n["pose_miss"] == 0 and n["missing_extrinsics"] == 0, status.message
    assert n["sets_completed"] >= 20 and n["outputs"] >= 3
    assert n["sets_completed"] == n["outputs"] + n["stale_sets_dropped"], counters
    assert n["sets_waited"] >= 1
    assert all(counters[f"extrinsics {c}"] == source for c in CAMS), counters
    # honest diagnostics: no ERROR at all before the first output, /tf_static never named
    # missing
    first_output = next(i for i, array in enumerate(h.received["diagnostics"])
                        for s in array.status if "odg_node" in s.name
                        and int({kv.key: kv.value for kv in s.values}["outputs"]) > 0)
    statuses = [s for array in h.received["diagnostics"] for s in array.status
                if "odg_node" in s.name]
    before = [s for array in h.received["diagnostics"][:first_output] for s in array.status
              if "odg_node" in s.name]
    assert before and all(s.level != ERROR for s in before), \
        [s.message for s in before if s.level == ERROR]
    assert not any("/tf_static" in s.message for s in statuses)
    assert child.poll() is None
    log.seek(0)
    text = log.read()
    assert "Traceback" not in text
    return text


def test_keyframe_tf_at_2_hz_with_wide_gaps_under_sim_time(ros_context, rclpy_module,
                                                           checkpoint, start_node):  # noqa
    child, params, log = start_node(checkpoint, pose_source="tf", use_sim_time=True,
                                    **SLOW_MODEL)
    assert params["extrinsics_source"] == "auto"              # the default
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)
    encoded = encoded_sets()
    # the bag starts after more than no_output_timeout + pose_wait: no ERROR for that
    h.spin_until(lambda: False, 6.5)
    start = 1000.0
    keyframes = start + np.concatenate([[0.0], np.cumsum(KEYFRAME_GAPS)])
    player = Player(h, start, sim_time=True)
    TFMessage = h.classes["TFMessage"]
    for t in keyframes:
        transforms = [tf_transform(h, "map", "base_link", float(t), pose_at(float(t), start))]
        transforms += [tf_transform(h, "base_link", c, float(t), RIG.cameras[c].sensor2ego)
                       for c in CAMS]
        player.at(float(t), lambda m=TFMessage(transforms=transforms): h.tf.publish(m))
    player.cameras(start, keyframes[-1] - OFFSETS[-1], encoded)
    player.play()
    check_the_run(h, child, log, "tf")


def test_bursty_late_odometry_without_tf(ros_context, rclpy_module, checkpoint,
                                         start_node):  # noqa: F811
    child, params, log = start_node(checkpoint, pose_source="odometry", **SLOW_MODEL)
    h = Harness(rclpy_module, ros_context)
    h.wait_for_node(child, log)
    encoded = encoded_sets()
    start = time.time() + 1.0                       # stamps in wall time: the node's clock
    player = Player(h, start, sim_time=False)
    stamps = np.arange(start - 0.2, start + 4.0, 0.02)
    for burst in np.arange(start, start + 4.5, 0.5):
        batch = [float(t) for t in stamps if burst - 0.5 < t <= burst]

        def publish(batch=batch):
            for t in batch:
                h.publish_pose(t, pose_at(t, start))
                time.sleep(0.001)      # best-effort reader, depth 100: a gentle burst
        player.at(float(burst) + 0.001, publish)
    player.cameras(start, start + 3.9, encoded)
    player.play()
    text = check_the_run(h, child, log, "rig file")
    assert "CAM_FRONT: no TF base_link -> CAM_FRONT in the data: its extrinsics come from " \
        "the rig file" in text
