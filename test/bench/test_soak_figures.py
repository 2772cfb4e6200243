"""odg soak's figures from hand-made records (odg_ros/bench/soak_report.py): scenes told apart by the
outputs' stamps, every history reset explained by a new scene or by outputs further apart than
history_max_gap or else unexplained, the wall latency of a looping replay's repeated stamps,
memory growth after the warm-up, the rate the replay achieved."""
from __future__ import annotations

import pytest

from odg_ros.bench.soak_report import (achieved_rate, output_scenes, summarize, verdicts,
                                wall_latencies)

A, B = 1000.0, 5000.0          # two bags of 10 s each, far apart in time


def record(outputs, resets=(), rss=None, processing=None, latency=None, announced=None):
    """outputs: (arrival, stamp); resets: (time of the diagnostics report, kind) each."""
    diagnostics, counts = [], {"gap": 0, "time_backwards": 0, "teleport": 0}
    for t in range(0, 61):
        for when, kind in resets:
            if t - 1 < when <= t:
                counts[kind] += 1
        diagnostics.append((float(t), 0, "running", dict(
            outputs=sum(o[0] <= t for o in outputs), sets_completed=400,
            stale_sets_dropped=300, **{f"history_resets_{k}": v for k, v in counts.items()})))
    return {"rate": 1.0, "wall_s": 60.0, "history_max_gap": 1.0,
            "bags": [{"path": "a", "start": A, "end": A + 10}, {"path": "b", "start": B,
                                                                "end": B + 10}],
            "outputs": [(t, stamp, [200.0]) for t, stamp in outputs],
            "processing_ms": [(t, 150.0) for t, _ in outputs] if processing is None
            else processing,
            "latency_ms": [(t, 180.0) for t, _ in outputs] if latency is None else latency,
            "diagnostics": diagnostics, "rss": rss or [(float(t), 500 * 2 ** 20) for t in
                                                       range(60)],
            "announced": announced or [], "node_exit": None}


# scene a (0.5 s apart), then b, then a again (the loop): 3 scenes
OUTPUTS = [(1.0, A + 1.0), (1.5, A + 1.5), (2.0, A + 2.0),
           (12.0, B + 0.5), (12.5, B + 1.0),
           (22.0, A + 0.2), (22.5, A + 0.7), (25.0, A + 3.0)]   # the last: 2.3 s after


def test_scenes_come_from_the_stamps():
    assert output_scenes(record(OUTPUTS)) == [0, 0, 0, 1, 1, 2, 2, 2]
    # one bag looping on its own: a stamp going back is a new scene
    alone = record([(1.0, A + 1.0), (2.0, A + 2.0), (12.0, A + 0.5)])
    assert output_scenes(alone) == [0, 0, 1]


def test_every_reset_is_explained_or_named_unexplained():
    explained = record(OUTPUTS, resets=[(12.0, "gap"), (21.8, "time_backwards"),
                                        (24.9, "gap")])
    resets = summarize(explained)["resets"]
    assert resets["at_scene_changes"] == 2 and resets["new_scenes_without_reset"] == 0
    assert resets["outputs_further_apart_than_history_max_gap"] == 1
    assert resets["unexpected"] == [] and resets["total"] == 3
    # a reset with no new scene nor a slow output near it; and a new scene without one
    broken = record(OUTPUTS, resets=[(12.0, "gap"), (40.0, "teleport"), (24.9, "gap")])
    resets = summarize(broken)["resets"]
    assert resets["unexpected"] == [{"t": 40.0, "kind": "teleport"}]
    assert resets["new_scenes_without_reset"] == 1
    checks = {c["target"].split(" (")[0]: c["met"] for c in verdicts([summarize(broken)])}
    assert checks["every history reset explained"] is False
    # a slow output explains a gap reset only, not a jump back in time
    wrong_kind = record(OUTPUTS, resets=[(12.0, "gap"), (21.8, "time_backwards"),
                                         (24.9, "time_backwards")])
    assert len(summarize(wrong_kind)["resets"]["unexpected"]) == 1


def test_a_reset_counted_before_its_output_arrives_is_matched():
    """The history restarts as the step begins; the output comes a step later."""
    slow = record(OUTPUTS, resets=[(12.0, "gap"), (21.8, "time_backwards"), (24.9, "gap")],
                  processing=[(t, 2500.0) for t, _ in OUTPUTS])
    slow["outputs"] = [(t + 2.4, stamp, since) for t, stamp, since in slow["outputs"]]
    assert summarize(slow)["resets"]["unexpected"] == []


def test_wall_latency_picks_the_arrival_of_the_image_the_output_was_made_of():
    """A short bag looping: the same stamp came twice; the newer arrival came after the set
    was complete (less than its processing time before the output): not its image."""
    r = record([(10.0, A + 1.0)], processing=[(10.0, 900.0)])
    r["outputs"] = [(10.0, A + 1.0, [5000.0, 1000.0, 300.0])]
    assert wall_latencies(r) == [(10.0, 1000.0)]
    r["outputs"] = [(10.0, A + 1.0, [])]
    assert wall_latencies(r) == [(10.0, None)]


def test_memory_growth_after_the_warm_up_and_the_rate_achieved():
    growing = record(OUTPUTS, rss=[(float(t), (500 + (t > 30) * 30) * 2 ** 20)
                                   for t in range(60)])
    rss = summarize(growing, warmup_s=20.0)["rss"]
    assert rss["warmup_s"] == 20.0 and rss["growth_after_warmup_mb"] == pytest.approx(30.0)
    assert rss["peak_mb"] == 530.0 and rss["slope_mb_per_hour"] > 0
    # two levels 26 MB apart, the low one for most of the first half, the high one for
    # most of the second (the allocator handing buffers back and taking them again): no
    # growth (a median of either half would say 26 MB)
    levels = [509 + 26 * (t % 7 == 0 if t < 45 else t % 7 != 0) for t in range(60)]
    swinging = record(OUTPUTS, rss=[(float(t), mb * 2 ** 20) for t, mb in enumerate(levels)])
    assert summarize(swinging, warmup_s=30.0)["rss"]["growth_after_warmup_mb"] == \
        pytest.approx(0.0)
    flat = summarize(record(OUTPUTS), warmup_s=300.0)["rss"]
    assert flat["warmup_s"] == 30.0 and flat["growth_after_warmup_mb"] == 0.0
    # bags of 10 s announced 5 s apart: 2x
    r = record(OUTPUTS, announced=[(0.0, 1, "a"), (5.0, 2, "b"), (10.0, 1, "a")])
    assert achieved_rate(r) == pytest.approx(2.0)
    assert achieved_rate(record(OUTPUTS)) is None


def test_the_node_latency_of_an_output_published_after_a_jump_is_left_out():
    """Published in the next scene's bag time: the jump, not the node."""
    r = record(OUTPUTS, latency=[(t, 180.0) for t, _ in OUTPUTS])
    r["latency_ms"][4] = (12.5, -3000.0)                       # the clock went back
    r["latency_ms"][2] = (2.0, (B - A) * 1e3)                  # on into bag b
    s = summarize(r)
    assert s["node_latency_ms_bag"]["p99"] == pytest.approx(180.0)


def test_a_restart_output_made_of_an_image_from_before_the_restart_is_stale():
    from odg_ros.bench.soak_report import summarize_restarts
    r = record([(10.0, A + 1.0), (30.0, A + 5.0), (31.0, A + 6.0)],
               processing=[(10.0, 500.0), (30.0, 500.0), (31.0, 500.0)])
    r["restarts"] = [{"killed_s": 20.0, "started_s": 20.5, "up_after_s": 5.0,
                      "first_output_after_s": 9.5, "first_output_index": 1,
                      "first_report_index": 21}]
    # each output's image arrived 0.6 s before it; the last one's only before the restart
    r["outputs"] = [(10.0, A + 1.0, [600.0]), (30.0, A + 5.0, [600.0]),
                    (31.0, A + 6.0, [11_000.0])]
    summary = summarize_restarts(r)["restarts"][0]
    assert (summary["outputs"], summary["stale_outputs"], summary["errors"]) == (2, 1, 0)
    checks = {c["target"]: c["met"] for c in verdicts([], restarts=summarize_restarts(r))}
    assert checks["after a restart nothing stale is published, no ERROR"] is False
    assert checks["after a SIGKILL, the first output at most 10 s after the restart"] is True


def test_errors_during_a_stall_of_the_whole_machine_are_counted_apart():
    """No memory sample for 10 s (the soak itself stood still): the ERRORs from then until
    STALL_RECOVERY_S after are the node reporting the stall; one later is not."""
    stalled = [(float(t), 500 * 2 ** 20) for t in range(60) if not 5 < t < 15]
    r = record(OUTPUTS, rss=stalled)
    for t in (15.0, 40.0, 58.0):         # in the stall's wake, its recovery, then after it
        r["diagnostics"][int(t)] = (t, 2, "no output for 6.0 s while inputs arrive", {})
    r["diagnostics"][-1] = r["diagnostics"][-2]       # the last report carries the counters
    summary = summarize(r)
    assert summary["machine_stalls"] == [{"at_s": 5.0, "seconds": 10.0}]
    assert summary["statuses"]["error"] == 3
    assert summary["statuses"]["error_in_machine_stalls"] == 2
    check = next(c for c in verdicts([summary]) if c["target"].startswith("no ERROR"))
    assert check["met"] is False and check["measured"].startswith("1x: 1 (2 more during 1")
    # without the late one, met; without the stall, all three count
    r["diagnostics"][58] = (58.0, 0, "running", {})
    assert next(c for c in verdicts([summarize(r)]) if c["target"].startswith("no ERROR"))["met"]
    r["rss"] = [(float(t), 500 * 2 ** 20) for t in range(60)]
    summary = summarize(r)
    assert summary["machine_stalls"] == [] and summary["statuses"]["error_in_machine_stalls"] == 0
