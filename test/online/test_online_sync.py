"""Camera set synchronisation: jitter, reordering, dropped cameras, duplicates, time jumps."""
import random

import pytest

from odg_ros.online.sync import CameraSetSync

CAMS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
        "CAM_BACK_RIGHT")
# nuScenes-like: a set every 1/12 s, cameras 0..42 ms after the set start (docs/architecture.md sec. 2)
OFFSETS = (0.0, 0.008, 0.017, 0.025, 0.033, 0.042)
PERIOD = 1 / 12


def messages(num_sets, start=100.0, jitter=0.0, seed=0):
    rng = random.Random(seed)
    out = []
    for k in range(num_sets):
        for cam, offset in zip(CAMS, OFFSETS):
            stamp = start + k * PERIOD + offset + rng.uniform(-jitter, jitter)
            out.append((cam, stamp, (k, cam)))
    return out


def feed(sync, msgs):
    sets = []
    for cam, stamp, payload in msgs:
        sets += sync.add(cam, stamp, payload)
    return sets


def assert_clean_set(camera_set, k):
    assert list(camera_set.stamps) == list(CAMS)
    assert all(payload == (k, cam) for cam, payload in camera_set.payloads.items())
    assert camera_set.span <= 0.05


def test_in_order_sets_complete_one_by_one():
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, messages(5))
    assert len(sets) == 5
    for k, s in enumerate(sets):
        assert_clean_set(s, k)
        assert s.reference_camera == "CAM_FRONT"
        assert s.reference_stamp == pytest.approx(100.0 + k * PERIOD)
    assert sync.counters["dropped_incomplete"] == 0 and sync.num_pending == 0


def test_jitter_and_reordering_within_and_across_sets():
    # +-3 ms of jitter, and messages shuffled within a window of two sets
    msgs = messages(20, jitter=0.003, seed=1)
    rng = random.Random(2)
    shuffled = []
    for i in range(0, len(msgs), 12):
        chunk = msgs[i:i + 12]
        rng.shuffle(chunk)
        shuffled += chunk
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, shuffled)
    # A set completed after a newer set is dropped (it can no longer be emitted in order);
    # every emitted set is clean and the emitted sequence is strictly increasing in time.
    assert len(sets) + sync.counters["dropped_incomplete"] == 20
    assert len(sets) >= 10
    for s in sets:
        k = s.payloads["CAM_FRONT"][0]
        assert_clean_set(s, k)
    refs = [s.reference_stamp for s in sets]
    assert refs == sorted(refs)


def test_reordering_inside_one_set_loses_nothing():
    msgs = messages(10, jitter=0.002, seed=3)
    reordered = []
    for k in range(10):
        chunk = msgs[6 * k:6 * k + 6]
        reordered += chunk[::-1]          # newest camera first, every set
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, reordered)
    assert [s.payloads["CAM_BACK"][0] for s in sets] == list(range(10))
    assert sync.counters["dropped_incomplete"] == 0


def test_missing_message_drops_that_set_only_and_counts_it():
    msgs = [m for m in messages(6) if not (m[2] == (2, "CAM_BACK_LEFT"))]
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, msgs)
    assert [s.payloads["CAM_FRONT"][0] for s in sets] == [0, 1, 3, 4, 5]
    assert sync.counters["dropped_incomplete"] == 1
    assert sync.num_pending == 0


def test_dead_camera_keeps_memory_bounded():
    msgs = [m for m in messages(50) if m[0] != "CAM_BACK"]
    sync = CameraSetSync(CAMS, slop=0.05, max_pending=4)
    assert feed(sync, msgs) == []
    assert sync.num_pending == 4
    assert sync.counters["dropped_incomplete"] == 46
    # the camera comes back: sets flow again
    sets = feed(sync, messages(3, start=100.0 + 50 * PERIOD))
    assert len(sets) == 3


@pytest.mark.parametrize("num_sets", [8, 9, 12])
def test_a_set_dropped_for_room_is_not_dropped_again_when_its_lagging_camera_comes(num_sets):
    """One camera lags (a reader matched late gets its backlog in a burst): the oldest waiting
    sets are dropped to stay within max_pending, and that camera's messages for them are late,
    not new partial sets to drop a second time: each set is emitted or dropped exactly once,
    however many sets behind the camera is (the dropped sets were once remembered only up to
    max_pending: 9 sets counted 10 dropped, 12 sets 16)."""
    msgs = messages(num_sets)
    sync = CameraSetSync(CAMS, slop=0.05, max_pending=4)
    assert feed(sync, [m for m in msgs if m[0] != "CAM_BACK"]) == []
    behind = num_sets - 4
    assert sync.counters["dropped_incomplete"] == behind     # the oldest sets, for room
    sets = feed(sync, [m for m in msgs if m[0] == "CAM_BACK"])
    assert [s.payloads["CAM_FRONT"][0] for s in sets] == list(range(behind, num_sets))
    assert sync.counters["late_messages"] == behind
    assert sync.counters["dropped_incomplete"] == behind
    assert sync.num_pending == 0


def test_sets_dropped_for_room_are_forgotten_after_the_time_jump_window():
    """A dead camera: the sets dropped for room are remembered only as long as a late message
    of theirs could still come (time_jump), so memory stays bounded."""
    sync = CameraSetSync(CAMS, slop=0.05, max_pending=4, time_jump=1.0)
    feed(sync, [m for m in messages(120) if m[0] != "CAM_BACK"])    # 10 s
    assert sync.counters["dropped_incomplete"] == 116
    assert len(sync._evicted) <= 13                                 # 1 s of sets at 12 Hz


# The demo bag's rig (odg_ros/data/synth/sensor_rig.py, as nuScenes): the cameras fire 0..42.6 ms
# after the set start, in this order, and the next set starts 40.7 ms after the last camera:
# closer than the slop, so the last camera of a set also fits the first ones of the next.
BAG_OFFSETS = {"CAM_FRONT_LEFT": 0.0, "CAM_FRONT": 0.0076, "CAM_FRONT_RIGHT": 0.0155,
               "CAM_BACK_RIGHT": 0.0230, "CAM_BACK": 0.0327, "CAM_BACK_LEFT": 0.0426}


@pytest.mark.parametrize("stalled", [0, 2])
def test_the_last_camera_of_a_set_joins_its_own_set_not_the_next_one(stalled):
    """The node's executor stalls (inference on a loaded machine) while set ``stalled`` is
    half taken; the next round takes one message per ready camera topic, in subscription
    order (the model's camera order), so CAM_FRONT_LEFT of the next set comes before
    CAM_BACK_LEFT of this one. CAM_BACK_LEFT fits both within the slop; it belongs to its own
    set. (Joining the next set's lone CAM_FRONT_LEFT instead made a third partial set out of
    two: 2 sets lost, 3 counted dropped_incomplete -- odg demo's unaccounted = -1 seen in CI.)"""
    def message(k, cam):
        return cam, 100.0 + k / 12 + BAG_OFFSETS[cam], (k, cam)

    in_bag_order = sorted(BAG_OFFSETS, key=BAG_OFFSETS.get)
    msgs = []
    for k in range(6):
        if k == stalled:
            msgs += [message(k, c) for c in in_bag_order[:3]]
            ready = [message(k, c) for c in in_bag_order[3:]] + [message(k + 1, in_bag_order[0])]
            msgs += sorted(ready, key=lambda m: CAMS.index(m[0]))
        elif k == stalled + 1:
            msgs += [message(k, c) for c in in_bag_order[1:]]
        else:
            msgs += [message(k, c) for c in in_bag_order]
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, msgs)
    assert sync.counters["sets_emitted"] + sync.counters["dropped_incomplete"] == 6
    assert [s.payloads["CAM_FRONT"][0] for s in sets] == list(range(6))
    for k, s in enumerate(sets):
        assert_clean_set(s, k)
    assert sync.num_pending == 0


def executor_run(published, stalls, seed):
    """The node's single-threaded executor, modelled: one queue per camera topic (sensor QoS:
    keep last 5, the oldest overwritten), a stall drawn from ``stalls`` between rounds, each
    round taking one message per ready topic in subscription order. published: (publish time,
    camera, key, stamp) -> (the sync, the sets it emitted, the keys of the sets it saw)."""
    in_bag_order = sorted(BAG_OFFSETS, key=BAG_OFFSETS.get)
    published = sorted((t, in_bag_order.index(cam), cam, key, stamp)
                       for t, cam, key, stamp in published)
    rng = random.Random(seed)
    queues = {c: [] for c in CAMS}
    sync = CameraSetSync(CAMS, slop=0.05)
    seen, sets, now = set(), [], 0.0
    while published or any(queues.values()):
        now += rng.choice(stalls)
        while published and published[0][0] <= now:
            _, _, cam, key, stamp = published.pop(0)
            queues[cam] = (queues[cam] + [(stamp, key)])[-5:]
        for cam in CAMS:
            if queues[cam]:
                stamp, key = queues[cam].pop(0)
                seen.add(key)
                sets += sync.add(cam, stamp, (key, cam))
    return sync, sets, seen


def test_every_set_is_emitted_or_dropped_once_whatever_the_executor_stalls():
    """The executor model (executor_run) with stalls of 2 ms to 0.9 s between rounds: whatever
    the stalls, each set the sync saw a message of is emitted or counted dropped_incomplete
    exactly once."""
    stalls = (0.002, 0.002, 0.005, 0.01, 0.03, 0.06, 0.1, 0.2, 0.4, 0.6, 0.9)
    for seed in range(200):
        sync, sets, seen = executor_run([(k / 12 + BAG_OFFSETS[c], c, k, 100.0 + k / 12
                                          + BAG_OFFSETS[c]) for k in range(13) for c in CAMS],
                                        stalls, seed)
        for s in sets:
            assert_clean_set(s, s.payloads["CAM_FRONT"][0])
        assert len(sets) + sync.counters["dropped_incomplete"] == len(seen), seed
        assert sync.num_pending == 0, seed


def test_a_bag_loop_with_a_camera_message_from_before_it_taken_after_it():
    """The bag loops from 200 s back to 100 s while the executor still holds CAM_BACK_RIGHT of
    the last set before the loop: it is taken after the first message after the loop, and is
    late. (Taken as a new set, it moved the newest stamp back to 200 s, so the next message
    made a second time jump: the first set after the loop lost, counted dropped twice.)"""
    sync = CameraSetSync(CAMS, slop=0.05, time_jump=1.0)
    before, after = messages(3, start=200.0), messages(4, start=100.0)
    straggler = before.pop()
    assert straggler[0] == "CAM_BACK_RIGHT"
    sets = feed(sync, before + after[:1] + [straggler] + after[1:])
    assert [s.payloads["CAM_FRONT"][0] for s in sets] == [0, 1, 0, 1, 2, 3]
    assert sync.counters["time_jumps"] == 1
    assert sync.counters["late_messages"] == 1
    assert sync.counters["dropped_incomplete"] == 1     # set 2 before the loop, once
    assert sync.num_pending == 0


def test_every_set_is_emitted_or_dropped_once_when_the_bag_loops():
    """The executor model (executor_run), the bag played twice (its stamps jump back 13 sets): one
    time jump, and each set seen is emitted or dropped exactly once (before the fix above, 62
    of these 200 executor schedules miscounted, with two jumps)."""
    for seed in range(200):
        sync, sets, seen = executor_run(
            [(loop * 13 / 12 + k / 12 + BAG_OFFSETS[c], c, (loop, k),
              100.0 + k / 12 + BAG_OFFSETS[c]) for loop in (0, 1) for k in range(13)
             for c in CAMS], (0.002, 0.002, 0.005, 0.01, 0.03, 0.06, 0.1), seed)
        for s in sets:
            assert len({payload[0] for payload in s.payloads.values()}) == 1, seed
        assert len(sets) + sync.counters["dropped_incomplete"] == len(seen), seed
        assert sync.counters["time_jumps"] == 1, seed
        assert sync.num_pending == 0, seed


def test_cameras_fired_together_with_noisy_stamps_still_make_every_set():
    """A rig whose cameras fire together but are stamped on arrival (+-20 ms of noise): every
    set spans under the slop, so every set is made. (Rejecting a message whose stamp, less its
    camera's offset in the last set, is more than the slop from a set's lost sets here: one
    set's offsets are noise for the next.)"""
    rng = random.Random(3)
    msgs = [(cam, 100.0 + k * PERIOD + rng.uniform(-0.02, 0.02), (k, cam))
            for k in range(60) for cam in CAMS]
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, msgs)
    assert [s.payloads["CAM_FRONT"][0] for s in sets] == list(range(60))
    for k, s in enumerate(sets):
        assert_clean_set(s, k)


def test_late_message_after_its_set_was_dropped():
    msgs = messages(3)
    late = [m for m in msgs if m[2] == (1, "CAM_BACK")]
    rest = [m for m in msgs if m[2] != (1, "CAM_BACK")]
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, rest)
    assert [s.payloads["CAM_FRONT"][0] for s in sets] == [0, 2]
    assert feed(sync, late) == []
    assert sync.counters["late_messages"] == 1
    assert sync.counters["dropped_incomplete"] == 1


def test_duplicate_stamps_are_dropped():
    msgs = messages(2)
    doubled = []
    for m in msgs:
        doubled += [m, (m[0], m[1], "copy")]
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = feed(sync, doubled)
    assert len(sets) == 2
    for k, s in enumerate(sets):
        assert_clean_set(s, k)
    # the copies of the last message of each set arrive after it was emitted: late
    assert sync.counters["duplicate_messages"] + sync.counters["late_messages"] == 12


def test_sets_farther_apart_than_slop_never_mix():
    # Two half sets 60 ms apart must not be merged into one set
    sync = CameraSetSync(CAMS, slop=0.05)
    out = []
    for i, cam in enumerate(CAMS):
        out += sync.add(cam, 10.0 + (0.06 if i >= 3 else 0.0), i)
    assert out == []
    assert sync.num_pending == 2


def test_time_jump_backwards_restarts():
    sync = CameraSetSync(CAMS, slop=0.05, time_jump=1.0)
    first = feed(sync, messages(5, start=200.0))
    again = feed(sync, messages(5, start=100.0))      # the bag looped
    assert len(first) == 5 and len(again) == 5
    assert sync.counters["time_jumps"] == 1
    assert sync.counters["late_messages"] == 0


def test_sets_waiting_at_a_time_jump_are_counted_dropped():
    """The bag loops while two sets wait for cameras: they can never complete, and each set
    seen is still emitted or counted dropped once."""
    sync = CameraSetSync(CAMS, slop=0.05, time_jump=1.0)
    first = messages(3, start=200.0)
    waiting = [m for m in first if m[0] != "CAM_BACK" or m[1] < 200.05]  # sets 2, 3 lack one
    assert len(feed(sync, waiting)) == 1 and sync.num_pending == 2
    again = feed(sync, messages(2, start=100.0))
    assert len(again) == 2 and sync.counters["time_jumps"] == 1
    assert sync.counters["dropped_incomplete"] == 2 and sync.num_pending == 0


def test_small_step_backwards_is_late_not_a_jump():
    sync = CameraSetSync(CAMS, slop=0.05, time_jump=1.0)
    feed(sync, messages(5, start=200.0))
    assert feed(sync, messages(1, start=199.8)) == []
    assert sync.counters["time_jumps"] == 0
    assert sync.counters["late_messages"] == 6


def test_bad_settings_and_unknown_camera():
    with pytest.raises(ValueError):
        CameraSetSync(CAMS, slop=0.0)
    with pytest.raises(ValueError):
        CameraSetSync(("A", "A"))
    with pytest.raises(ValueError):
        CameraSetSync(CAMS).add("CAM_SIDE", 1.0, None)
