"""A complete set whose poses (or camera transforms) have not arrived yet waits for them,
bounded by pose_wait on the node's clock, as tf2's message filter holds a message: the
waiting room on its own (online/waiting.py, a fake clock), then the pipeline replaying the
layouts of public nuScenes converters in log-time order: /tf at 2 Hz keyframes with gaps of
0.55 and 0.75 s, and odometry written in bursts up to 0.5 s after its stamps. Every
completed set is prepared or dropped as stale; none is a pose miss."""
import functools
import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

from odg_ros.geometry import make_transform
from odg_ros.online.errors import BadInput
from odg_ros.online.extrinsics import CameraExtrinsics
from odg_ros.online.images import EncodedImage
from odg_ros.online.pipeline import OnlinePipeline, PipelineSettings
from odg_ros.online.predictor import OnlinePredictor
from odg_ros.online.transforms import TransformBuffer
from odg_ros.online.waiting import FAILED, PENDING, READY, WaitingSets
from testing.online import (CAMS, HW, OFFSETS, RIG, feed_set, make_model, png, scaled_K,
                            set_images)


# ------------------------------------------------------------------ the waiting room
@dataclass
class Item:
    reference_stamp: float
    waited: float = 0.0
    expired: bool = False


class Data:
    """What the probe sees: sets up to ``newest`` are ready, those in ``failing`` fail for
    good, the others wait."""

    def __init__(self):
        self.newest = -1.0
        self.failing = set()
        self.probes = []

    def probe(self, item, final):
        self.probes.append((item.reference_stamp, final))
        if item.reference_stamp in self.failing:
            return FAILED
        return READY if item.reference_stamp <= self.newest else PENDING


def room(wait=1.0, clock=None, **kwargs):
    data = Data()
    clock = clock if clock is not None else [100.0]
    return WaitingSets(data.probe, wait, lambda: clock[0], **kwargs), data, clock


def test_a_set_waits_for_its_data_and_goes_as_soon_as_it_comes():
    waiting, data, clock = room()
    item = Item(10.0)
    waiting.put(item)
    assert waiting.get(timeout=0) is None and len(waiting) == 1
    clock[0] += 0.4
    data.newest = 10.0
    waiting.notify()
    assert waiting.get(timeout=0) is item
    assert item.waited == pytest.approx(0.4) and not item.expired
    assert (waiting.waited, waiting.expired, waiting.dropped, len(waiting)) == (1, 0, 0, 0)


def test_the_newest_ready_set_wins_and_the_older_ones_are_dropped_as_stale():
    waiting, data, clock = room()
    items = [Item(10.0 + k / 12) for k in range(6)]
    for item in items:
        waiting.put(item)
    assert waiting.get(timeout=0) is None
    data.newest = items[3].reference_stamp                 # a keyframe between sets 3 and 4
    waiting.notify()
    assert waiting.get(timeout=0) is items[3]
    assert waiting.dropped == 3 and len(waiting) == 2      # 0-2 stale, 4-5 still wait
    data.newest = 20.0
    waiting.notify()
    assert waiting.get(timeout=0) is items[5] and waiting.dropped == 4


def test_a_set_whose_wait_runs_out_is_handed_on_expired_after_a_last_probe():
    waiting, data, clock = room(wait=1.0)
    old, new = Item(10.0), Item(10.5)
    waiting.put(old)
    clock[0] += 0.5
    waiting.put(new)
    clock[0] += 0.49
    assert waiting.get(timeout=0) is None                  # the node clock: 0.99 s waited
    clock[0] += 0.02
    assert waiting.get(timeout=0) is old and old.expired and old.waited == pytest.approx(1.01)
    assert data.probes[-1] == (10.0, True)                 # the last chance: final
    assert waiting.get(timeout=0) is None and len(waiting) == 1   # the newer one waits on
    assert (waiting.expired, waiting.dropped) == (1, 0)


def test_the_wait_runs_on_the_node_clock_and_on_the_steady_clock_while_that_stands_at_0():
    steady = [0.0]
    waiting, data, clock = room(wait=1.0, steady=lambda: steady[0])
    waiting.put(Item(10.0))
    steady[0] += 0.2
    clock[0] += 0.9                                 # a replay at 4.5x: bag time counts
    assert waiting.get(timeout=0) is None
    clock[0] += 0.1
    assert waiting.get(timeout=0).expired
    sim_time_before_clock = WaitingSets(data.probe, 1.0, lambda: 0.0,
                                        steady=lambda: steady[0])
    sim_time_before_clock.put(Item(10.0))
    assert sim_time_before_clock.get(timeout=0) is None
    steady[0] += 1.0
    assert sim_time_before_clock.get(timeout=0).expired


def test_a_set_never_waits_forever_when_the_node_clock_stops():
    """A replay that ended (or paused): its /clock stands still and what the set waits for
    does not come; the steady seconds waited since the clock stopped count."""
    steady = [0.0]
    waiting, data, clock = room(wait=1.0, steady=lambda: steady[0])
    first, second = Item(10.0), Item(10.1)
    waiting.put(first)
    steady[0] += 0.5
    clock[0] += 0.5                                 # the clock runs for half a second...
    waiting.put(second)
    for _ in range(9):                              # ...then stands still: 0.9 s, waiting
        steady[0] += 0.1
        assert waiting.get(timeout=0) is None
    steady[0] += 0.1
    assert waiting.get(timeout=0) is first and first.expired
    assert first.waited == pytest.approx(1.0)
    assert waiting.get(timeout=0) is second and second.expired and len(waiting) == 0
    # the clock moving again: node time counts again, from where it is
    third = Item(12.0)
    clock[0] += 1.5
    waiting.put(third)
    steady[0] += 0.5
    clock[0] += 0.5
    assert waiting.get(timeout=0) is None
    clock[0] += 0.5
    assert waiting.get(timeout=0) is third and third.waited == pytest.approx(1.0)


def test_wait_zero_never_waits():
    waiting, data, clock = room(wait=0.0)
    item = Item(10.0)
    waiting.put(item)
    assert waiting.get(timeout=0) is item and item.expired


def test_a_time_jump_or_a_looped_clock_drops_the_waiting_sets_as_stale():
    waiting, data, clock = room()
    waiting.put(Item(10.0))
    waiting.put(Item(10.1))
    waiting.put(Item(3.0))                        # synchronisation restarted (a bag loop)
    assert waiting.dropped == 2 and len(waiting) == 1
    clock[0] -= 30.0                              # the sim clock went back with the bag
    assert waiting.get(timeout=0) is None and waiting.dropped == 3 and len(waiting) == 0


def test_the_room_is_bounded():
    waiting, data, clock = room(capacity=4)
    for k in range(10):
        waiting.put(Item(10.0 + k))
    assert len(waiting) == 4 and waiting.dropped == 6


def test_a_set_failing_for_good_is_handed_on_at_once_on_its_own():
    """It is counted as what it is (a gap too wide...), not hidden as stale; the sets
    around it wait on."""
    waiting, data, clock = room()
    items = [Item(10.0), Item(10.1), Item(10.2)]
    data.failing.add(10.1)
    for item in items:
        waiting.put(item)
    assert waiting.get(timeout=0) is items[1] and not items[1].expired
    assert (waiting.waited, waiting.dropped, len(waiting)) == (0, 0, 2)
    data.newest = 10.2
    waiting.notify()
    assert waiting.get(timeout=0) is items[2] and waiting.dropped == 1


def test_the_producers_never_wait_for_a_probe():
    """put and notify come from the input callbacks: a slow probe in the consumer's thread
    (look-ups under a busy lock) must not hold them."""
    release = threading.Event()

    def slow_probe(item, final):
        release.wait(5.0)
        return READY

    waiting = WaitingSets(slow_probe, 1.0, lambda: 100.0)
    waiting.put(Item(10.0))
    got = []
    consumer = threading.Thread(target=lambda: got.append(waiting.get(timeout=5.0)))
    consumer.start()
    time.sleep(0.05)                              # the consumer is inside the probe
    start = time.monotonic()
    waiting.put(Item(10.1))
    waiting.notify()
    elapsed = time.monotonic() - start
    release.set()
    consumer.join(5.0)
    assert elapsed < 0.05, elapsed
    assert got and got[0] is not None


def test_the_consumer_wakes_when_data_arrives():
    waiting, data, clock = room(poll=10.0)        # no polling: only the notify wakes it
    waiting.put(Item(10.0))
    got = []
    consumer = threading.Thread(target=lambda: got.append(waiting.get(timeout=5.0)))
    consumer.start()
    time.sleep(0.05)
    start = time.monotonic()
    data.newest = 10.0
    waiting.notify()
    consumer.join(5.0)
    assert got and got[0].reference_stamp == 10.0
    assert time.monotonic() - start < 1.0


@pytest.mark.parametrize("sets_before", [0, 1])
def test_the_consumer_sleeps_while_nothing_waits(sets_before):
    """An empty room (at the start, or once its sets are taken) blocks the consumer until
    a set comes: a loop instead holds the GIL and slows the model's thread (the first
    inference of a node took 16 times its time)."""
    readings = [0]

    def clock():
        readings[0] += 1
        return 100.0

    waiting = WaitingSets(lambda item, final: READY, 1.0, clock)
    for k in range(sets_before):
        waiting.put(Item(10.0 + k))
        assert waiting.get(timeout=1.0) is not None
    readings[0] = 0
    assert waiting.get(timeout=0.3) is None
    assert readings[0] < 10, f"{readings[0]} clock readings in 0.3 s of waiting"


# ---------------------------------------------------------------- the pipeline, replayed
def pose_at(t):
    """10 m/s, turning at 0.2 rad/s: linear interpolation over 1 s is off by ~0.25 m."""
    yaw = 0.2 * t
    return make_transform([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)],
                          (10.0 * np.sin(0.2 * t) / 0.2, 10.0 * (1 - np.cos(0.2 * t)) / 0.2,
                           0.0))


@pytest.fixture(scope="module")
def model_and_cfg():
    return make_model()


class Replay:
    """Events in log-time order on a fake node clock; after each, the consumer takes every
    set that is ready and prepares it (look-ups, decoding: the model is not what is tested),
    as the node's decoding thread does when it keeps up."""

    def __init__(self, model_and_cfg, pose_source, extrinsics="rig", camera_info=True,
                 **settings):
        model, cfg = model_and_cfg
        self.clock = [0.0]
        settings = PipelineSettings.from_parameters(CAMS, **settings)
        self.tf = TransformBuffer(max_interpolation_gap=settings.max_pose_gap,
                                  max_speed=settings.max_speed,
                                  max_acceleration=settings.max_acceleration)
        self.notes = []
        self.extrinsics = CameraExtrinsics(extrinsics, "base_link", self.tf, RIG,
                                           lambda level, m: self.notes.append((level, m)))
        pose_lookup = (lambda t: self.tf.lookup("map", "base_link", t, "pose_miss")) \
            if pose_source == "tf" else None
        predictor = OnlinePredictor(model, cfg, "cpu", max_gap=2.0)
        self.pipeline = OnlinePipeline(predictor, settings, self.extrinsics, pose_lookup,
                                       clock=lambda: self.clock[0])
        if camera_info:
            for name in CAMS:
                self.pipeline.on_camera_info(name, scaled_K(name), *HW, frame_id=name)
        self.events = []
        self.prepared, self.errors = [], []

    def at(self, log_time, action):
        self.events.append((log_time, len(self.events), action))

    def run(self, flush=2.0):
        for log_time, _, action in sorted(self.events):
            self.clock[0] = log_time
            action()
            self.drain()
        self.clock[0] += flush                  # long after the last message
        self.drain()
        return self.pipeline.counters()

    def drain(self):
        while (camera_set := self.pipeline.next_set(timeout=0)) is not None:
            try:
                prepared = self.pipeline.prepare(camera_set)
                self.prepared.append((camera_set.reference_stamp, prepared))
            except BadInput as error:
                self.errors.append(error)

    def cameras(self, start, stop, delay=0.005):
        """Sets every 1/12 s, each delivered when its last camera's image is logged."""
        self.sets = int(round((stop - start) * 12)) + 1
        for m in range(self.sets):
            t = start + m / 12
            self.at(t + OFFSETS[-1] + delay, lambda t=t, m=m: self.feed(t, m))

    def feed(self, start, m):
        for name, offset, image in zip(CAMS, OFFSETS, encoded_images(m % 3)):
            self.pipeline.on_image(name, start + offset, image, now=self.clock[0])

    def keyframe_tf(self, stamps, cameras_on_tf=False):
        """/tf at keyframes only, logged at their stamps: map -> base_link (and base_link ->
        every camera, all dynamic, as a public converter writes them)."""
        for t in stamps:
            def publish(t=t):
                self.tf.add("map", "base_link", t, pose_at(t))
                if cameras_on_tf:
                    for name in CAMS:
                        self.tf.add("base_link", name, t, RIG.cameras[name].sensor2ego)
                self.pipeline.transforms_arrived()
            self.at(t, publish)


@functools.lru_cache(maxsize=None)
def encoded_images(seed):
    return [EncodedImage(True, "png", png(image)) for image in set_images(seed)]


KEYFRAMES = np.cumsum([10.0, 0.5, 0.55, 0.5, 0.75, 0.5, 0.5, 0.5])   # gaps 0.55 and 0.75


def accounted(counters, replay):
    """Every completed set was prepared or dropped as stale."""
    assert counters["sets_waiting"] == 0
    return counters["sets_completed"] == len(replay.prepared) + counters["stale_sets_dropped"]


@pytest.mark.parametrize("cameras_on_tf", [False, True])
def test_keyframe_tf_with_gaps_of_0_55_and_0_75_s_no_pose_miss(model_and_cfg, cameras_on_tf):
    replay = Replay(model_and_cfg, "tf", extrinsics="auto" if cameras_on_tf else "rig")
    replay.keyframe_tf(KEYFRAMES, cameras_on_tf)
    replay.cameras(KEYFRAMES[0], KEYFRAMES[-1] - OFFSETS[-1])
    counters = replay.run()
    assert counters["pose_miss"] == 0 and counters["missing_extrinsics"] == 0, replay.errors
    assert accounted(counters, replay)
    assert counters["sets_completed"] == replay.sets and counters["sets_waited"] >= 7
    # the newest set ready at each keyframe wins: about one per keyframe, in stamp order
    stamps = [s for s, _ in replay.prepared]
    assert stamps == sorted(stamps) and len(stamps) >= len(KEYFRAMES) - 1
    # each prepared set's poses are the keyframes' interpolation, not a guess
    for stamp, prepared in replay.prepared:
        assert np.allclose(prepared.reference_pose[:3, 3], pose_at(stamp)[:3, 3], atol=0.35)
    if cameras_on_tf:
        assert set(replay.extrinsics.sources(CAMS).values()) == {"tf"}
        assert not replay.notes                 # TF equals the rig file: nothing to say


@pytest.mark.parametrize("broken", [dict(pose_wait=0.0), dict(max_pose_gap=0.5)])
def test_keyframe_tf_without_the_wait_or_with_the_old_gap_bound_misses(model_and_cfg, broken):
    """The same replay with no waiting, or the former 0.5 s bound: pose misses (what users
    saw before), so the test above does test the mechanism."""
    replay = Replay(model_and_cfg, "tf", **broken)
    replay.keyframe_tf(KEYFRAMES)
    replay.cameras(KEYFRAMES[0], KEYFRAMES[-1] - OFFSETS[-1])
    counters = replay.run()
    assert counters["pose_miss"] >= 2                # at least one per wide gap


def bursty_odometry(replay, start, stop, delay=0.5):
    """Odometry at 50 Hz, written in bursts every ``delay`` s of log time carrying the
    stamps since the last burst (up to ``delay`` s behind)."""
    stamps = np.arange(start - 0.2, stop + 0.05, 0.02)
    bursts = np.arange(start, stop + delay, delay)
    for log_time in bursts:
        batch = stamps[(stamps <= log_time) & (stamps > log_time - delay)]

        def publish(batch=batch):
            for t in batch:
                replay.pipeline.on_pose(float(t), pose_at(float(t)))
        replay.at(log_time + 0.001, publish)


def test_bursty_late_odometry_no_pose_miss(model_and_cfg):
    replay = Replay(model_and_cfg, "odometry")
    bursty_odometry(replay, 10.0, 14.0)
    replay.cameras(10.0, 13.9)
    counters = replay.run()
    assert counters["pose_miss"] == 0, replay.errors
    assert accounted(counters, replay) and counters["sets_waited"] >= 7
    assert len(replay.prepared) >= 8
    for stamp, prepared in replay.prepared:     # 50 Hz: interpolation is near exact
        assert np.allclose(prepared.reference_pose, pose_at(stamp), atol=1e-3)
    broken = Replay(model_and_cfg, "odometry", pose_wait=0.0)
    bursty_odometry(broken, 10.0, 14.0)
    broken.cameras(10.0, 13.9)
    assert broken.run()["pose_miss"] >= 30                 # nearly all, as users saw


def test_a_wait_that_runs_out_is_a_pose_miss_that_says_so(model_and_cfg):
    replay = Replay(model_and_cfg, "odometry", pose_wait=0.8)
    replay.at(10.0, lambda: [replay.pipeline.on_pose(t, pose_at(t)) for t in (9.6, 10.0)])
    replay.at(10.05, lambda: feed_set(replay.pipeline, 10.3, set_images(0), now=10.05))
    counters = replay.run(flush=0.5)         # the odometry stopped: nothing after 10.0
    assert counters["pose_miss"] == 0 and counters["sets_waiting"] == 1
    replay.clock[0] += 0.3
    replay.drain()
    assert replay.pipeline.counters()["pose_miss"] == 1
    message = replay.errors[0].message
    assert message.startswith("still missing after waiting 0.80 s (pose_wait 0.8 s): ")
    assert "no pose at t=10.3" in message


def test_extrinsics_auto_without_tf_waits_once_then_takes_the_rig_file(model_and_cfg):
    """A bag without TF (poses from odometry): the first set waits pose_wait for camera
    transforms, then every camera takes the rig file, logged once; no set is lost."""
    replay = Replay(model_and_cfg, "odometry", extrinsics="auto")
    replay.at(9.9, lambda: [replay.pipeline.on_pose(float(t), pose_at(float(t)))
                            for t in np.arange(9.5, 13.0, 0.02)])
    replay.cameras(10.0, 12.0)
    counters = replay.run()
    assert counters["missing_extrinsics"] == 0 and accounted(counters, replay)
    assert replay.prepared[0][0] == pytest.approx(10.0)   # the first set waited, then went
    assert set(replay.extrinsics.sources(CAMS).values()) == {"rig file"}
    infos = [m for level, m in replay.notes if level == "info"]
    assert len(infos) == len(CAMS) and "CAM_FRONT: no TF base_link -> CAM_FRONT" in infos[0]


def camera_info_after_the_first_set(replay, late, never=()):
    """Poses all along; the first set's images at 10.0 s, each camera's first CameraInfo
    logged with its image, except ``late`` ones read 20 ms after the set completed (the
    executor ran their callbacks after the image's) and ``never`` ones never sent."""
    replay.at(9.9, lambda: [replay.pipeline.on_pose(float(t), pose_at(float(t)))
                            for t in np.arange(9.5, 12.5, 0.02)])
    replay.cameras(10.0, 11.0)
    first_done = 10.0 + OFFSETS[-1] + 0.005
    for name, offset in zip(CAMS, OFFSETS):
        if name not in never:
            replay.at(first_done + 0.02 if name in late else 10.0 + offset - 1e-4,
                      lambda name=name: replay.pipeline.on_camera_info(
                          name, scaled_K(name), *HW, frame_id=name))


def test_a_set_completed_before_its_last_camera_info_waits_for_it(model_and_cfg):
    replay = Replay(model_and_cfg, "odometry", camera_info=False)
    camera_info_after_the_first_set(replay, late={CAMS[-1]})
    counters = replay.run()
    assert counters["missing_camera_info"] == 0, replay.errors
    assert accounted(counters, replay) and counters["sets_waited"] >= 1
    assert replay.prepared[0][0] == pytest.approx(10.0)      # the first set is not lost
    broken = Replay(model_and_cfg, "odometry", camera_info=False, pose_wait=0.0)
    camera_info_after_the_first_set(broken, late={CAMS[-1]})
    assert broken.run()["missing_camera_info"] == 1           # the race, without the wait


def test_a_camera_info_that_never_comes_is_missing_after_the_wait(model_and_cfg):
    replay = Replay(model_and_cfg, "odometry", camera_info=False, pose_wait=0.5)
    camera_info_after_the_first_set(replay, late=(), never={CAMS[2]})
    counters = replay.run()
    assert counters["missing_camera_info"] >= 1 and not replay.prepared
    assert counters["sets_waiting"] == 0 and counters["sets_completed"] == \
        counters["missing_camera_info"] + counters["stale_sets_dropped"]
    message = replay.errors[0].message
    assert message.startswith("still missing after waiting 0.50 s (pose_wait 0.5 s): ")
    assert f"no valid CameraInfo yet for ['{CAMS[2]}']" in message


def test_the_decoding_thread_waits_for_a_late_pose(model_and_cfg):
    """The node's path: sets prepared in their own thread, on the steady clock."""
    model, cfg = model_and_cfg
    pipeline = OnlinePipeline(OnlinePredictor(model, cfg, "cpu", max_gap=2.0),
                              PipelineSettings.from_parameters(CAMS, pose_wait=5.0),
                              lambda camera, frame, t: RIG.cameras[camera].sensor2ego)
    for name in CAMS:
        pipeline.on_camera_info(name, scaled_K(name), *HW, frame_id=name)
    bad = []
    pipeline.start_decoding(bad.append, lambda: bad.append("internal error"))
    try:
        pipeline.on_pose(9.8, pose_at(9.8))
        feed_set(pipeline, 10.0, set_images(0))
        assert pipeline.next_prepared(timeout=0.3) is None     # its pose has not come
        pipeline.on_pose(10.2, pose_at(10.2))
        prepared = pipeline.next_prepared(timeout=10.0)
        assert prepared is not None and prepared.camera_set.reference_stamp == 10.0
        assert prepared.camera_set.waited > 0.2 and not bad
        assert pipeline.counters()["sets_waited"] == 1
    finally:
        pipeline.close()


def test_a_first_camera_info_wakes_the_waiting_room(model_and_cfg):
    """The decoding thread sleeps until news (or its poll): a camera's first CameraInfo is
    news; a repeated one (with every image) is not."""
    model, cfg = model_and_cfg
    pipeline = OnlinePipeline(OnlinePredictor(model, cfg, "cpu"),
                              PipelineSettings.from_parameters(CAMS),
                              lambda camera, frame, t: RIG.cameras[camera].sensor2ego)
    woken = []
    pipeline.waiting.notify = lambda: woken.append(True)
    try:
        pipeline.on_camera_info(CAMS[0], scaled_K(CAMS[0]), *HW, frame_id=CAMS[0])
        assert len(woken) == 1
        pipeline.on_camera_info(CAMS[0], scaled_K(CAMS[0]), *HW, frame_id=CAMS[0])
        assert len(woken) == 1
    finally:
        pipeline.close()


def test_the_first_set_after_a_jump_forward_waits_for_the_new_poses(model_and_cfg):
    """Bags of two scenes back to back, the second much later: its first set completes
    before its first /tf; the pose buffer holds only the first scene's. It waits, then
    goes; no pose miss."""
    replay = Replay(model_and_cfg, "tf")
    replay.keyframe_tf([10.0, 10.5, 11.0])
    replay.cameras(10.0, 10.9)
    later = 5000.0
    replay.at(later + OFFSETS[-1] + 0.005, lambda: replay.feed(later, 0))

    def new_scene_poses():       # the new bag's first /tf messages, read after the images
        for t in later + 0.02 * np.arange(26):
            replay.tf.add("map", "base_link", float(t), pose_at(float(t)))
        replay.pipeline.transforms_arrived()
    replay.at(later + 0.1, new_scene_poses)
    counters = replay.run()
    assert counters["pose_miss"] == 0, replay.errors
    assert replay.prepared[-1][0] == pytest.approx(later)
