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


def test_the_no_output_error_names_the_topics_that_never_sent():
    """A wrong image topic pattern: camera infos and odometry arrive, images never."""
    clock = [0.0]
    inputs, stats = make(clock)
    for k in range(70):
        clock[0] = 0.1 * k
        inputs.received("/CAM_FRONT/camera_info")
        inputs.received("/odom")
        status = stats.status({"sets_completed": 0})
    assert status["level"] == diagnostics.ERROR
    assert "no output for 6.9 s while inputs arrive: no complete camera set" \
        in status["message"]
    assert status["message"].endswith("never received: /CAM_FRONT/image, /CAM_BACK/image")
    values = dict(status["values"])
    assert values["/CAM_BACK/image: received"] == "0"
    assert values["/CAM_BACK/image: seconds since last"] == "n/a"
    early = make([1.0])[1].status({})                    # before any output: named too
    assert "waiting for the first complete camera set" in early["message"]
    assert "never received: " + ", ".join(TOPICS) in early["message"]
