"""Diagnostics in the right clock: whatever the node's clock does (sim time paused, a bag
that stopped), rates and "no input for N s" follow the steady clock; per input topic the
messages received and the seconds since the last one; the no-output ERROR names the topics
that never sent (online/diagnostics.py)."""
from odg_ros.online import diagnostics

TOPICS = ["/CAM_FRONT/image", "/CAM_BACK/image", "/CAM_FRONT/camera_info", "/odom"]


def make(clock):
    inputs = diagnostics.InputMonitor(TOPICS, clock=lambda: clock[0])
    return inputs, diagnostics.PipelineStats(stale_after_s=5.0, clock=lambda: clock[0],
                                             inputs=inputs)


def test_when_the_inputs_stop_the_rate_falls_and_it_says_so():
    clock = [0.0]
    inputs, stats = make(clock)
    for k in range(30):                                  # 3 s at 10 Hz, everything arrives
        clock[0] = 0.1 * k
        for topic in TOPICS:
            inputs.received(topic)
        # the node's clock is frozen (a paused sim clock): the stamp age says so, the
        # steady latency does not care
        stats.record_output(image_stamp=50.0, now=50.0, timings={}, received=clock[0] - 0.2)
    status = stats.status({})
    assert status["level"] == diagnostics.OK and "running at 10.0 Hz" in status["message"]
    values = dict(status["values"])
    assert values["receipt_to_publish_p50_ms (steady)"] == "200.0"
    assert values["stamp_age_p50_ms (node clock)"] == "0.0"
    assert values["/odom: received"] == "30"
    assert values["/odom: seconds since last"] == "0.0"
    clock[0] = 12.0                                      # the bag stopped 9.1 s ago
    status = stats.status({})
    assert status["level"] == diagnostics.WARN
    assert status["message"].startswith("no input for 9.1 s (last output 9.1 s ago)")
    assert stats.rate_hz() == 0.0
    assert dict(status["values"])["/odom: seconds since last"] == "9.1"


def test_no_error_before_the_first_complete_set_and_the_topics_it_waits_for_named():
    """A wrong image topic pattern: camera infos and odometry arrive, images never. The node
    is waiting, not failing: WARN naming the topics it waits for, never ERROR."""
    clock = [0.0]
    inputs, stats = make(clock)
    for k in range(300):                                 # 30 s of inputs but no image
        clock[0] = 0.1 * k
        inputs.received("/CAM_FRONT/camera_info")
        inputs.received("/odom")
        status = stats.status({"sets_completed": 0})
        assert status["level"] == diagnostics.WARN, status["message"]
    assert status["message"] == ("waiting for the first complete camera set; never "
                                 "received: /CAM_FRONT/image, /CAM_BACK/image")
    values = dict(status["values"])
    assert values["/CAM_BACK/image: received"] == "0"
    assert values["/CAM_BACK/image: seconds since last"] == "n/a"
    early = make([1.0])[1].status({})                    # before any input: named too
    assert "waiting for the first complete camera set" in early["message"]
    assert "never received: " + ", ".join(TOPICS) in early["message"]


def test_the_no_output_timer_starts_at_the_first_complete_set():
    """The node started 8 s before the bag: no ERROR a second after the first images (the
    timer used to count from the start). Sets that never give an output are an ERROR
    no_output_timeout after the first one completed, naming the dominant reason."""
    clock = [0.0]
    inputs, stats = make(clock)
    counters = {"sets_completed": 0, "pose_miss": 0}
    levels = {}
    for k in range(200):                                  # 20 s at 10 Hz
        clock[0] = 0.1 * k
        if clock[0] >= 8.0:                               # the bag starts playing
            for topic in TOPICS:
                inputs.received(topic)
            if k % 2 == 0:                                # 5 sets/s, every one a pose miss
                stats.record_complete_set()
                counters["sets_completed"] += 1
                counters["pose_miss"] += 1
        status = stats.status(dict(counters))
        levels[round(clock[0], 1)] = status["level"]
    assert all(level == diagnostics.WARN for t, level in levels.items() if t <= 13.0)
    assert levels[13.2] == diagnostics.ERROR
    assert "no output for 11.9 s while inputs arrive: 100 % of dropped sets and inputs " \
        "were pose_miss" in status["message"]
    assert "never received" not in status["message"]


def test_the_first_set_may_wait_pose_wait_before_the_timer_runs():
    clock = [0.0]
    inputs, _ = make(clock)
    stats = diagnostics.PipelineStats(stale_after_s=5.0, clock=lambda: clock[0], inputs=inputs,
                                      first_set_grace_s=1.0)
    stats.record_complete_set()
    for t, level in ((5.9, diagnostics.WARN), (6.1, diagnostics.ERROR)):
        clock[0] = t
        for topic in TOPICS:
            inputs.received(topic)
        status = stats.status({"sets_completed": 1, "pose_miss": 1})
        assert status["level"] == level, status["message"]
    assert status["message"].startswith("no output for 5.1 s while inputs arrive")


def test_never_received_names_only_the_topics_the_configuration_needs():
    """/tf_static is optional when transforms can come from /tf; with camera transforms from
    TF but poses from odometry, one of /tf and /tf_static is needed."""
    inputs = diagnostics.InputMonitor()
    for topic in ("/CAM_FRONT/image", "/odom"):
        inputs.watch(topic)
    inputs.watch("/tf")
    inputs.watch("/tf_static", needed=False)
    stats = diagnostics.PipelineStats(clock=lambda: 1.0, inputs=inputs)
    inputs.received("/CAM_FRONT/image")
    inputs.received("/odom")
    assert stats.status({})["message"].endswith("never received: /tf")
    inputs.received("/tf")
    assert "never received" not in stats.status({})["message"]
    assert dict(stats.status({})["values"])["/tf_static: received"] == "0"    # reported

    needed = diagnostics.transform_topics_needed
    assert needed("tf", "auto") == needed("tf", "tf") == needed("tf", "rig") == (True, False)
    assert needed("odometry", "tf") == (False, True)
    assert needed("odometry", "auto") == needed("odometry", "rig") == (False, False)
    either = diagnostics.InputMonitor()
    either.watch("/tf", needed=False)
    either.watch("/tf_static", needed=False)
    either.need_one_of(("/tf", "/tf_static"))
    assert either.never_received() == ["/tf or /tf_static"]
    either.received("/tf_static")
    assert either.never_received() == []


def test_the_extrinsics_source_of_each_camera_is_reported():
    stats = diagnostics.PipelineStats(clock=lambda: 1.0)
    values = dict(stats.status({}, extrinsics={"CAM_FRONT": "tf", "CAM_BACK": "rig file"})
                  ["values"])
    assert values["extrinsics CAM_FRONT"] == "tf" and values["extrinsics CAM_BACK"] == \
        "rig file"
