"""Hard cases of the node's inputs, on the ROS-free functions (odg_ros/online/images.py,
sync.py, poses.py): corrupt and truncated JPEGs, wrong image sizes and encodings, empty
messages, out-of-order and duplicated stamps, stamps far in the future or the past.

The contract under test: every input either gives a correct result or a ``BadInput`` with a
specific kind (the node logs, counts and skips it) -- never another exception (a crash of
the node) and never a silently wrong result.

Already covered by test_online_images.py / test_online_sync.py / test_online_poses.py (fixed
cases, not repeated): a half-length JPEG, empty bytes, BMP, 16-bit PNG, raw buffer checks,
in-set reordering, duplicates, dead camera, time jump backwards, pose extrapolation bound.
Here hypothesis fuzzes the bytes and the stamp streams.
"""
import io
import math
import random

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from odg_ros.geometry import make_transform
from odg_ros.online.errors import BadInput
from odg_ros.online.images import (RAW_ENCODINGS, EncodedImage, decode, decode_for_input,
                                   to_network_input)
from odg_ros.online.poses import PoseBuffer
from odg_ros.online.sync import CameraSetSync

from testing.hard_cases import FEW, FUZZ, HARD

INPUT_HW = (64, 176)
K = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 180.0], [0.0, 0.0, 1.0]])


def jpeg_bytes(h=72, w=128, seed=0, quality=90):
    rng = np.random.default_rng(seed)
    smooth = np.linspace(0, 255, w)[None, :, None] * np.ones((h, 1, 3))
    image = np.clip(smooth + rng.normal(0, 20, (h, w, 3)), 0, 255).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


JPEG = jpeg_bytes()
JPEG_HW = (72, 128)


def decode_all_ways(data, fmt="jpeg", expected_hw=JPEG_HW, reduced_decode=True):
    """Full decode, reduced decode (the node's path) and the network input, or the
    BadInput kind. reduced_decode=False: the full decode feeds the network input."""
    image = EncodedImage(compressed=True, format=fmt, data=data)
    try:
        full = decode(image)
        if reduced_decode:
            reduced, original_hw = decode_for_input(image, INPUT_HW)
        else:
            reduced, original_hw = full, tuple(full.shape[:2])
        net, K2 = to_network_input(reduced, expected_hw, K, INPUT_HW, original_hw)
    except BadInput as error:
        return error.kind
    assert full.dtype == np.uint8 and full.ndim == 3 and full.shape[2] == 3
    assert tuple(full.shape[:2]) == original_hw == expected_hw
    assert net.shape == (*INPUT_HW, 3) and net.dtype == np.uint8 and np.isfinite(K2).all()
    return "ok"


# ------------------------------------------------------------------------------ images
@FUZZ
@given(cut=st.integers(0, len(JPEG) - 1))
def test_jpeg_truncated_anywhere(cut):
    # all but the last 2 bytes (the end-of-image marker) is truncated scan data
    assert decode_all_ways(JPEG[:cut]) in ({"corrupt_image"} if cut < len(JPEG) - 2
                                           else {"corrupt_image", "ok"})


CORRUPTIONS = st.lists(st.tuples(st.integers(0, len(JPEG) - 1), st.integers(1, 255)),
                       min_size=1, max_size=8)


def corrupt(flips):
    data = bytearray(JPEG)
    for position, xor in flips:
        data[position] ^= xor
    return bytes(data)


@FUZZ
@given(flips=CORRUPTIONS)
def test_jpeg_with_corrupted_bytes_full_decode(flips):
    """Flipped bytes in the headers or the scan: a BadInput, or (scan damage JPEG cannot
    detect) an image of the size its header declares -- the CameraInfo check then decides."""
    assert decode_all_ways(corrupt(flips), reduced_decode=False) in {
        "ok", "corrupt_image", "unsupported_encoding", "wrong_image_size"}


SCAN_START = JPEG.index(b"\xff\xda") + 2 + int.from_bytes(JPEG[JPEG.index(b"\xff\xda") + 2:
                                                               JPEG.index(b"\xff\xda") + 4],
                                                          "big")


@FUZZ
@given(flips=st.lists(st.tuples(st.integers(SCAN_START, len(JPEG) - 1), st.integers(1, 255)),
                      min_size=1, max_size=8))
def test_jpeg_with_corrupted_scan_data_reduced_decode(flips):
    """The node's path (reduced decode) with the entropy-coded data damaged, headers intact:
    a BadInput or an image of the declared size, never a crash."""
    assert decode_all_ways(corrupt(flips)) in {"ok", "corrupt_image"}


def test_jpeg_with_corrupted_size_header_reduced_decode():
    data = corrupt([(165, 99)])
    assert decode_all_ways(data) in {"corrupt_image", "wrong_image_size"}


@FUZZ
@given(data=st.binary(max_size=300), fmt=st.sampled_from(["jpeg", "png", "", "rgb8; jpeg"]))
def test_random_bytes_are_corrupt_images(data, fmt):
    assert decode_all_ways(data, fmt) == "corrupt_image"


@pytest.mark.parametrize("data,fmt,kind", [
    (b"", "jpeg", "corrupt_image"),
    (b"", "png", "corrupt_image"),
    (b"", "", "corrupt_image"),
    (JPEG[:2], "jpeg", "corrupt_image"),                     # the SOI marker alone
    (JPEG, "16UC1; compressedDepth", "unsupported_encoding"),
    (JPEG, "32FC1", "unsupported_encoding"),
    (JPEG, "png", "ok"),                                     # the content decides, not the name
    (JPEG, "", "ok"),
])
def test_empty_messages_and_format_strings(data, fmt, kind):
    assert decode_all_ways(data, fmt) == kind


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1", "bayer_rggb8", "yuv422", "RGB8",
                                      "rgb16", "", "jpeg"])
def test_raw_encodings_we_do_not_decode(encoding):
    image = EncodedImage(compressed=False, format=encoding, data=bytes(4 * 4 * 3), height=4,
                         width=4, step=12)
    with pytest.raises(BadInput) as error:
        decode(image)
    assert error.value.kind == "unsupported_encoding"


@FUZZ
@given(encoding=st.sampled_from(sorted(RAW_ENCODINGS)), h=st.integers(-1, 12),
       w=st.integers(-1, 12), extra_step=st.integers(-3, 5), missing=st.integers(-4, 40))
def test_raw_buffers_of_any_size(encoding, h, w, extra_step, missing):
    channels = RAW_ENCODINGS[encoding][0]
    step = max(w, 0) * channels + extra_step
    size = max(0, step * max(h, 0) - missing)
    image = EncodedImage(compressed=False, format=encoding, data=bytes(range(256)) * 8,
                         height=h, width=w, step=step)
    image.data = image.data[:size]
    try:
        rgb = decode(image)
    except BadInput as error:
        assert error.kind == "corrupt_image"
        return
    assert rgb.shape == (h, w, 3) and rgb.dtype == np.uint8   # decoded: exactly the header's


@FEW
@given(h=st.integers(1, 300), w=st.integers(1, 600), fmt=st.sampled_from(["JPEG", "PNG"]),
       info_hw=st.sampled_from(["same", "swapped", "off by one"]))
def test_odd_image_sizes_and_camera_info_mismatches(h, w, fmt, info_hw):
    """Image sizes from 1x1 up (aspect ratios up to 300:1) against a matching, a swapped or
    an off-by-one CameraInfo: a network input of the right size, or wrong_image_size."""
    buffer = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), 100, np.uint8)).save(buffer, format=fmt)
    expected = {"same": (h, w), "swapped": (w, h), "off by one": (h + 1, w)}[info_hw]
    kind = decode_all_ways(buffer.getvalue(), fmt.lower(), expected)
    assert kind == ("ok" if expected == (h, w) else "wrong_image_size")


@pytest.mark.parametrize("hw", [(1, 1000), (2, 1000), (1, 4000)])
def test_extremely_wide_images_are_a_bad_input_not_a_crash(hw):
    h, w = hw
    buffer = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), 100, np.uint8)).save(buffer, format="JPEG")
    assert decode_all_ways(buffer.getvalue(), "jpeg", (h, w)) in ("ok", "wrong_image_size")


# ------------------------------------------------------------------------------ sync
CAMS = ("F", "FR", "FL", "B", "BL", "BR")
OFFSETS = (0.0, 0.008, 0.017, 0.025, 0.033, 0.042)
PERIOD = 1 / 12


def check_emitted(sets, slop=0.05):
    previous = None
    for s in sets:
        assert list(s.stamps) == list(CAMS) and s.span <= slop + 1e-12
        assert all(s.payloads[c][1] == s.stamps[c] for c in CAMS)   # payload kept its stamp
        assert all(math.isfinite(v) for v in s.stamps.values())
        if previous is not None:
            assert min(s.stamps.values()) > max(previous.stamps.values())  # strictly in order
        previous = s


@FUZZ
@given(num_sets=st.integers(1, 12), start=st.sampled_from([0.0, 1.7e9, 4.1e9]),
       jitter=st.floats(0, 0.004), window=st.integers(1, 14), duplicates=st.floats(0, 0.3),
       drops=st.floats(0, 0.2), seed=st.integers(0, 2 ** 16))
def test_sync_out_of_order_and_duplicated_stamps(num_sets, start, jitter, window, duplicates,
                                                 drops, seed):
    """Messages reordered within a sliding window, duplicated (same stamp again) and
    dropped: every emitted set is complete, within slop, in strict time order, and a set
    none of whose messages was dropped or delayed beyond the next set is emitted."""
    rng = random.Random(seed)
    msgs, dropped_sets = [], set()
    for k in range(num_sets):
        for cam, offset in zip(CAMS, OFFSETS):
            stamp = start + k * PERIOD + offset + rng.uniform(-jitter, jitter)
            if rng.random() < drops:
                dropped_sets.add(k)
                continue
            msgs.append((cam, stamp, (k, stamp)))
            if rng.random() < duplicates:
                msgs.append((cam, stamp, (k, stamp)))
    order = sorted(range(len(msgs)), key=lambda i: i + rng.uniform(0, window))
    sync = CameraSetSync(CAMS, slop=0.05)
    sets = []
    for i in order:
        cam, stamp, payload = msgs[i]
        sets += sync.add(cam, stamp, payload)
        assert sync.num_pending <= sync.max_pending
    check_emitted(sets)
    emitted = {s.payloads["F"][0] for s in sets}
    assert emitted.isdisjoint(dropped_sets)
    if window == 1 and not dropped_sets:            # in order, nothing lost: all emitted
        assert emitted == set(range(num_sets))
    assert all(v >= 0 for v in sync.counters.values())


def stream(sync, first_set, num_sets, start=1000.0):
    out = []
    for k in range(first_set, first_set + num_sets):
        for cam, offset in zip(CAMS, OFFSETS):
            stamp = start + k * PERIOD + offset
            out += sync.add(cam, stamp, (k, stamp))
    return out


@pytest.mark.parametrize("glitch", [1e6, 3600.0, -3600.0, -1e6, 1.0, -0.9])
def test_sync_survives_one_message_far_in_the_future_or_past(glitch):
    """One message with a stamp far off (clock glitch, stale replay): at most the set in
    flight is lost, then synchronisation goes on by itself."""
    sync = CameraSetSync(CAMS, slop=0.05)
    before = stream(sync, 0, 5)
    stamp = 1000.0 + 5 * PERIOD + glitch
    glitched = sync.add("FR", stamp, (99, stamp))
    after = stream(sync, 5, 5)
    check_emitted(before + glitched + after)
    assert len(before) == 5 and not glitched
    assert {s.payloads["F"][0] for s in after} >= set(range(6, 10))


@pytest.mark.parametrize("stamp", [math.nan, math.inf, -math.inf])
def test_sync_rejects_non_finite_stamps(stamp):
    sync = CameraSetSync(CAMS[:2], slop=0.05)
    sync.add("F", 1.0, 1)
    sync.add("FR", 1.01, 2)
    for cam in CAMS[:2]:
        with pytest.raises((ValueError, BadInput)):
            sync.add(cam, stamp, None)
    assert not sync.add("F", 2.0, 3) and sync.add("FR", 2.01, 4)


# ------------------------------------------------------------------------------ poses
def pose_at(t):
    """Ego driving a circle of radius 50 m at 10 m/s (finite, smooth, any t)."""
    angle = 0.2 * (t % 1000.0)
    return make_transform(np.array([[math.cos(angle), -math.sin(angle), 0],
                                    [math.sin(angle), math.cos(angle), 0], [0, 0, 1.0]]),
                          [50 * math.sin(angle), 50 * (1 - math.cos(angle)), 0.0])


@HARD
@given(start=st.sampled_from([0.0, 1.7e9, 4.1e9]), n=st.integers(2, 40),
       seed=st.integers(0, 2 ** 16), duplicates=st.floats(0, 0.5))
def test_pose_buffer_with_out_of_order_and_duplicated_stamps(start, n, seed, duplicates):
    """Odometry at 50 Hz delivered shuffled, some stamps twice with a corrupted-then-fixed
    pose (the newer message wins): lookups at the stamps give the last pose sent for them;
    between them, interpolation of the neighbours; far outside, pose_miss."""
    rng = random.Random(seed)
    stamps = [start + 0.02 * i for i in range(n)]
    events = [(t, pose_at(t)) for t in stamps]
    for t in rng.sample(stamps, int(duplicates * n)):
        events.insert(rng.randrange(len(events) + 1), (t, pose_at(t + 5.0)))  # a stale copy
        events.append((t, pose_at(t)))                                        # corrected later
    rng.shuffle(events[: len(events) // 2])       # the early half arrives out of order
    buffer = PoseBuffer(max_extrapolation=0.05, max_interpolation_gap=0.5)
    for t, T in events:
        buffer.add(t, T)
    last = {}
    for t, T in events:
        last[t] = T
    for t in stamps:
        np.testing.assert_allclose(buffer.lookup(t), last[t], atol=1e-9)
    for far in (stamps[0] - 3600.0, stamps[-1] + 3600.0, stamps[-1] + 1e9, stamps[0] - 0.06):
        with pytest.raises(BadInput) as error:
            buffer.lookup(far)
        assert error.value.kind == "pose_miss"
    mid = stamps[0] + 0.01
    # float64 seconds at epoch 2100 resolve 0.5 us: the weight is the representable one
    alpha = (mid - stamps[0]) / (stamps[1] - stamps[0])
    expected_xy = (1 - alpha) * last[stamps[0]][:2, 3] + alpha * last[stamps[1]][:2, 3]
    np.testing.assert_allclose(buffer.lookup(mid)[:2, 3], expected_xy, atol=1e-9)


@pytest.mark.parametrize("stamp", [math.nan, math.inf, -math.inf])
def test_pose_buffer_rejects_non_finite_pose_stamps(stamp):
    buffer = PoseBuffer()
    with pytest.raises(BadInput) as error:
        buffer.add(stamp, np.eye(4))
    assert error.value.kind == "bad_pose" and len(buffer) == 0


@pytest.mark.parametrize("stamp", [math.inf, -math.inf, 1e300, -1e300])
def test_pose_lookup_far_in_the_future_or_past_is_a_pose_miss(stamp):
    buffer = PoseBuffer()
    buffer.add(10.0, np.eye(4))
    buffer.add(10.1, make_transform(np.eye(3), [1.0, 0, 0]))
    with pytest.raises(BadInput) as error:
        buffer.lookup(stamp)
    assert error.value.kind == "pose_miss"


def test_pose_lookup_at_nan_is_a_pose_miss():
    buffer = PoseBuffer()
    buffer.add(10.0, np.eye(4))
    buffer.add(10.1, make_transform(np.eye(3), [1.0, 0, 0]))
    with pytest.raises(BadInput) as error:
        buffer.lookup(math.nan)
    assert error.value.kind == "pose_miss"


@pytest.mark.parametrize("name,T", [
    ("nan", np.full((4, 4), math.nan)),
    ("scaled rotation", make_transform(1.1 * np.eye(3), [0, 0, 0])),
    ("reflection", make_transform(np.diag([1.0, -1.0, 1.0]), [0, 0, 0])),
    ("inf translation", make_transform(np.eye(3), [math.inf, 0, 0])),
])
def test_pose_buffer_rejects_non_rigid_poses_and_keeps_its_state(name, T):
    buffer = PoseBuffer()
    buffer.add(10.0, np.eye(4))
    buffer.add(10.1, make_transform(np.eye(3), [1.0, 0, 0]))
    with pytest.raises(BadInput) as error:
        buffer.add(10.05, T)
    assert error.value.kind == "bad_pose" and len(buffer) == 2
    np.testing.assert_allclose(buffer.lookup(10.05)[:3, 3], [0.5, 0, 0], atol=1e-12)
