"""odg_node end to end with real rclpy (the node in its own process): unknown space in every
output, the debug timing topics, per-topic input diagnostics on a steady timer ("no input for
N s" once the inputs stop, even on a sim clock that never ticks), and the no-output ERROR
naming the topics that never sent."""
from __future__ import annotations

import time

import numpy as np

from test_node import (CAMS, NODE, Harness, checkpoint, set_images,  # noqa: F401 (fixtures)
                       start_node)

FAST = dict(diagnostics_period=0.2, no_output_timeout=1.0)


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
    for key, topic in (("processing", "processing_time_ms"), ("latency", "pipeline_latency_ms")):
        h.node.create_subscription(Float64, f"{NODE}/debug/{topic}",
                                   lambda m, k=key: debug[k].append(m.data), 10)
    h.wait_for_node(child, log)
    t0 = time.time() - 5.0
    h.publish_infos()
    h.publish_poses(t0 - 0.5, t0 + 1.0, t0)
    h.publish_set(t0 + 0.2, set_images(0))
    assert h.spin_until(lambda: h.received["grid"] and h.received["bev"] and
                        h.received["cloud"] and debug["latency"], 60, child, log)
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
    assert float(latest_status(h)[0]["/test/odom: seconds since last"]) > 1.0


def test_no_output_names_the_topics_that_never_sent(ros_context, rclpy_module, checkpoint,
                                                    start_node):
    """A wrong image topic pattern: the camera infos and poses arrive, no image ever."""
    child, params, log = start_node(checkpoint, image_topic="/wrong/{camera}/image", **FAST)
    h = Harness(rclpy_module, ros_context)
    h.spin_until(lambda: h.node.count_subscribers(f"/wrong/{CAMS[0]}/image") > 0, 60,
                 child, log)
    def error():
        status = latest_status(h)[1]
        return status is not None and status.level == b"\x02"

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not error():
        h.publish_infos()
        h.publish_pose(time.time(), np.eye(4))
        h.spin_until(lambda: False, 0.1)
    status = latest_status(h)[1]
    assert error(), status.message
    assert "no output for" in status.message and "while inputs arrive" in status.message
    assert "never received: " + ", ".join(f"/wrong/{c}/image" for c in CAMS) \
        in status.message


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
    t0 = time.time() - 5.0
    h.publish_infos()
    h.publish_poses(t0 - 0.5, t0 + 1.0, t0)
    h.publish_set(t0 + 0.2, set_images(0))
    assert h.spin_until(lambda: h.received["grid"] and h.received["bev"], 60, child, log)
    assert len(h.received["grid"][-1].observed) == 0
    assert -1 not in set(h.received["bev"][-1].data)
