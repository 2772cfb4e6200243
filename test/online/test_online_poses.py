"""Pose interpolation (linear + slerp), the extrapolation and gap bounds, poses not received
yet (pending) against poses that cannot come, bad poses, the TF buffer, the motion checks on
sparse (2 Hz) poses."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from odg_ros.geometry import invert_transform, make_transform
from odg_ros.online.errors import BadInput
from odg_ros.online.poses import PoseBuffer, interpolate_pose, pose_from_xyz_xyzw
from odg_ros.online.transforms import TransformBuffer
from odg_ros.rotation import yaw_of


def yaw_pose(yaw, xyz=(0, 0, 0)):
    return make_transform(Rotation.from_euler("z", yaw).as_matrix(), xyz)


def test_interpolation_matches_scipy_reference_on_random_poses():
    rng = np.random.default_rng(0)
    for _ in range(50):
        r0, r1 = Rotation.random(2, random_state=rng.integers(1 << 31))
        t0, t1 = rng.normal(size=3) * 10, rng.normal(size=3) * 10
        a = rng.uniform()
        T = interpolate_pose(1.0, make_transform(r0.as_matrix(), t0), 3.0,
                             make_transform(r1.as_matrix(), t1), 1.0 + 2.0 * a)
        reference = Slerp([0, 1], Rotation.concatenate([r0, r1]))([a])[0].as_matrix()
        assert np.allclose(T[:3, :3], reference, atol=1e-9)
        assert np.allclose(T[:3, 3], t0 + a * (t1 - t0))


def test_buffer_interpolates_and_accepts_any_order():
    buffer = PoseBuffer(max_extrapolation=0.05)
    for stamp, yaw, x in [(10.2, 0.2, 2.0), (10.0, 0.0, 0.0), (10.1, 0.1, 1.0)]:
        buffer.add(stamp, yaw_pose(yaw, (x, 0, 0)))
    T = buffer.lookup(10.05)
    assert yaw_of(T) == pytest.approx(0.05) and T[0, 3] == pytest.approx(0.5)
    assert np.allclose(buffer.lookup(10.1), yaw_pose(0.1, (1, 0, 0)))


def test_extrapolation_bound():
    buffer = PoseBuffer(max_extrapolation=0.05)
    buffer.add(0.0, yaw_pose(0.0, (0, 0, 0)))
    buffer.add(0.1, yaw_pose(0.1, (1, 0, 0)))
    # within 50 ms: constant-velocity extrapolation, both ends
    T = buffer.lookup(0.14)
    assert T[0, 3] == pytest.approx(1.4) and yaw_of(T) == pytest.approx(0.14)
    assert buffer.lookup(-0.03)[0, 3] == pytest.approx(-0.3)
    for stamp in (0.151, -0.051, 5.0):
        with pytest.raises(BadInput) as error:
            buffer.lookup(stamp)
        assert error.value.kind == "pose_miss"


def test_pose_miss_on_empty_buffer_and_on_large_gap():
    buffer = PoseBuffer(max_interpolation_gap=0.5)
    with pytest.raises(BadInput, match="no pose received"):
        buffer.lookup(1.0)
    buffer.add(0.0, np.eye(4))
    assert np.allclose(buffer.lookup(0.02), np.eye(4))     # one pose: held within the bound
    buffer.add(2.0, np.eye(4))
    with pytest.raises(BadInput) as error:
        buffer.lookup(1.0)
    assert error.value.kind == "pose_miss"


@pytest.mark.parametrize("bad", [
    np.full((4, 4), np.nan),
    np.diag([1.0, 1.0, 2.0, 1.0]),                 # scaled, not orthonormal
    np.diag([1.0, 1.0, -1.0, 1.0]),                # reflection, det -1
    np.eye(3),                                      # wrong shape
])
def test_bad_poses_are_rejected(bad):
    buffer = PoseBuffer()
    with pytest.raises(BadInput) as error:
        buffer.add(1.0, bad)
    assert error.value.kind == "bad_pose"
    assert len(buffer) == 0
    with pytest.raises(BadInput, match="non-finite"):
        buffer.add(float("nan"), np.eye(4))


def test_buffer_is_bounded_and_restarts_on_a_bag_loop():
    buffer = PoseBuffer(capacity=10, time_jump=1.0)
    for i in range(25):
        buffer.add(100 + 0.01 * i, np.eye(4))
    assert len(buffer) == 10 and buffer.span[0] == pytest.approx(100.15)
    buffer.add(50.0, np.eye(4))
    assert len(buffer) == 1 and buffer.resets == 1


def test_transform_buffer_chains_static_and_dynamic_edges():
    tf = TransformBuffer(max_extrapolation=0.05)
    # map -> odom (static), odom -> base_link (dynamic), base_link -> CAM (static)
    map_from_odom = yaw_pose(0.3, (5, 1, 0))
    tf.add("map", "odom", 0.0, map_from_odom, static=True)
    tf.add("odom", "base_link", 1.0, yaw_pose(0.0, (0, 0, 0)))
    tf.add("odom", "base_link", 1.1, yaw_pose(0.2, (2, 0, 0)))
    base_from_cam = make_transform(Rotation.from_euler("xyz", [-90, 0, -90], degrees=True)
                                   .as_matrix(), (1.7, 0.0, 1.5))
    tf.add("base_link", "CAM_FRONT", 0.0, base_from_cam, static=True)

    expected_pose = map_from_odom @ yaw_pose(0.1, (1, 0, 0))
    assert np.allclose(tf.lookup("map", "base_link", 1.05), expected_pose)
    assert np.allclose(tf.lookup("base_link", "CAM_FRONT", 1.05), base_from_cam)
    assert np.allclose(tf.lookup("CAM_FRONT", "map", 1.05),
                       invert_transform(expected_pose @ base_from_cam))
    with pytest.raises(BadInput) as error:
        tf.lookup("map", "base_link", 2.0)
    assert error.value.kind == "pose_miss"
    with pytest.raises(BadInput) as error:
        tf.lookup("base_link", "CAM_BACK", 1.05, kind="missing_extrinsics")
    assert error.value.kind == "missing_extrinsics"
    with pytest.raises(BadInput) as error:
        tf.add("odom", "base_link", 1.2, np.diag([2.0, 1, 1, 1]))
    assert error.value.kind == "bad_pose"


def test_pose_from_ros_fields():
    r = Rotation.from_euler("z", 30, degrees=True)
    T = pose_from_xyz_xyzw([1, 2, 3], r.as_quat())           # scipy is (x, y, z, w) too
    assert np.allclose(T[:3, :3], r.as_matrix()) and np.allclose(T[:3, 3], [1, 2, 3])
    for translation, quaternion in [([np.nan, 0, 0], [0, 0, 0, 1]), ([0, 0, 0], [0, 0, 0, 0]),
                                    ([0, 0, 0], [0, 0, 0, 2.0]), ([0, 0, 0], [0, 0, np.inf, 1])]:
        with pytest.raises(BadInput) as error:
            pose_from_xyz_xyzw(translation, quaternion)
        assert error.value.kind == "bad_pose"


# ---------------------------------------------- sparse poses: the gap bound, "not yet"
def kind_and_pending(call, *args):
    try:
        call(*args)
    except BadInput as error:
        return error.kind, error.pending
    return "ok", False


def test_keyframe_gaps_of_nuscenes_are_interpolated_up_to_the_bound():
    """Poses at 2 Hz keyframes with one gap stretched to 0.55 s and one to 0.75 s (as
    scene-0061 has, and worse): interpolated across with the default bound (1 s), a miss
    for good across a gap wider than the bound."""
    stamps = [10.0, 10.5, 11.05, 11.55, 12.3, 12.8]
    default, narrow = PoseBuffer(), PoseBuffer(max_interpolation_gap=0.5)
    for t in stamps:
        for buffer in (default, narrow):
            buffer.add(t, yaw_pose(0.1 * t, (5.0 * t, 0, 0)))
    for t in (10.8, 11.3, 12.0):
        assert default.lookup(t)[0, 3] == pytest.approx(5.0 * t)
    assert kind_and_pending(narrow.lookup, 10.25) == ("ok", False)
    assert kind_and_pending(narrow.lookup, 10.8) == ("pose_miss", False)
    assert kind_and_pending(narrow.lookup, 12.0) == ("pose_miss", False)
    two_seconds = PoseBuffer()
    two_seconds.add(10.0, np.eye(4))
    two_seconds.add(12.0, np.eye(4))
    assert kind_and_pending(two_seconds.lookup, 11.0) == ("pose_miss", False)
    with pytest.raises(ValueError):
        PoseBuffer(max_interpolation_gap=0.0)


def test_a_pose_not_received_yet_is_pending_a_pose_that_cannot_come_is_not():
    buffer = PoseBuffer(max_extrapolation=0.05, max_interpolation_gap=1.0)
    assert kind_and_pending(buffer.lookup, 10.0) == ("pose_miss", True)   # nothing yet
    buffer.add(10.0, np.eye(4))
    buffer.add(10.5, make_transform(np.eye(3), [2.5, 0, 0]))
    assert kind_and_pending(buffer.lookup, 10.54) == ("ok", False)       # extrapolated
    assert kind_and_pending(buffer.lookup, 10.6) == ("pose_miss", True)  # the next may come
    assert kind_and_pending(buffer.lookup, 11.5) == ("pose_miss", True)  # still within 1 s
    # beyond the gap bound: poses after a dropout or a jump forward (the next scene's bag)
    # can still bracket it
    assert kind_and_pending(buffer.lookup, 11.51) == ("pose_miss", True)
    assert kind_and_pending(buffer.lookup, 10010.0) == ("pose_miss", True)
    assert kind_and_pending(buffer.lookup, 9.9) == ("pose_miss", False)  # older than all
    assert kind_and_pending(buffer.lookup, math.nan) == ("pose_miss", False)
    buffer.add(11.7, np.eye(4))                           # a gap of 1.2 s: too wide
    assert kind_and_pending(buffer.lookup, 11.0) == ("pose_miss", False)
    wide_end = PoseBuffer(max_extrapolation=0.05, max_interpolation_gap=0.5)
    wide_end.add(10.0, np.eye(4))
    wide_end.add(10.8, np.eye(4))
    # just beyond the newest, the two end poses too far apart to extrapolate from: the
    # next pose can still bracket the stamp
    assert kind_and_pending(wide_end.lookup, 10.82) == ("pose_miss", True)


def test_every_dynamic_tf_edge_takes_the_gap_bound_and_not_yet_is_pending():
    """map -> base_link and base_link -> CAM_FRONT both on /tf at 2 Hz (a public nuScenes
    converter): both interpolated across a 0.75 s gap with a bound of 1 s, a miss with 0.5."""
    cam = make_transform(Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix(),
                         (1.7, 0.0, 1.5))
    wide, narrow = TransformBuffer(), TransformBuffer(max_interpolation_gap=0.5)
    for tf in (wide, narrow):
        assert kind_and_pending(tf.lookup, "map", "base_link", 10.0) == ("pose_miss", True)
        for t in (10.0, 10.75):
            tf.add("map", "base_link", t, yaw_pose(0.1 * t, (5.0 * t, 0, 0)))
            tf.add("base_link", "CAM_FRONT", t, cam)
    assert wide.lookup("map", "base_link", 10.3)[0, 3] == pytest.approx(51.5)
    assert np.allclose(wide.lookup("base_link", "CAM_FRONT", 10.3), cam)
    assert kind_and_pending(narrow.lookup, "map", "base_link", 10.3) == ("pose_miss", False)
    assert kind_and_pending(narrow.lookup, "base_link", "CAM_FRONT", 10.3,
                            "missing_extrinsics") == ("missing_extrinsics", False)
    # beyond the newest keyframe: the next one may still come
    assert kind_and_pending(wide.lookup, "map", "CAM_FRONT", 11.0) == ("pose_miss", True)
    # a chain of a pending edge and one that fails for good fails for good
    wide.add("world", "map", 10.0, np.eye(4))
    wide.add("world", "map", 11.5, np.eye(4))                  # 1.5 s: too wide
    assert kind_and_pending(wide.lookup, "world", "CAM_FRONT", 11.0) == ("pose_miss", False)
    assert kind_and_pending(wide.lookup, "CAM_FRONT", "world", 11.0) == ("pose_miss", False)
    assert wide.connected("base_link", "CAM_FRONT") and not wide.connected("map", "CAM_BACK")
    assert kind_and_pending(wide.lookup, "base_link", "CAM_BACK", 10.3,
                            "missing_extrinsics") == ("missing_extrinsics", True)
    with pytest.raises(ValueError):
        TransformBuffer(max_interpolation_gap=0.0)


@pytest.mark.parametrize("gaps", [(0.5,), (0.55,), (0.75,), (1.0,), (0.5, 0.55, 0.5, 0.75)])
def test_sparse_true_poses_of_the_synthetic_worlds_are_never_implausible(synthetic_worlds,
                                                                         gaps):
    """The motion checks (max_speed 70 m/s, max_acceleration 30 m/s^2: the node's defaults)
    judge a 2 Hz stream by its mean velocities over 0.5-1 s: the synthetic worlds' true ego
    poses at keyframe gaps of 0.5 to 1 s (turns, stops, starts) are all accepted, and a
    60 m glitch at the next keyframe is still rejected (a position glitch e over gaps g reads
    as an acceleration of about e / g^2: caught from 7.5 m at 0.5 s, 30 m at 1 s)."""
    for world in synthetic_worlds:
        buffer = PoseBuffer(max_speed=70.0, max_acceleration=30.0)
        t, k = 0.0, 0
        while t <= world.duration:
            buffer.add(t, world.ego_pose(t))
            t, k = t + gaps[k % len(gaps)], k + 1
        assert len(buffer) == k and buffer.teleports == 0
        glitch = world.ego_pose(t)
        glitch[:3, 3] += (60.0, 0.0, 0.0)
        assert kind_and_pending(buffer.add, t, glitch) == ("implausible_motion", False)


@pytest.fixture(scope="module")
def synthetic_worlds():
    """odg synth's worlds: a right turn at 9.3 m/s on a 4 m radius (2.2 g: the harshest the
    generator makes), a left turn at 5.4 m/s (0.4 g), an open road with speed changes."""
    from odg_ros.data.synth.city import SceneKind
    from odg_ros.data.synth.generate import scene_world
    return [scene_world(0, 1, 20.0), scene_world(0, 7, 20.0),
            scene_world(1, 0, 8.0, SceneKind(roads="open-road"))]
