"""Pose interpolation (linear + slerp), the extrapolation bound, bad poses, the TF buffer."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from odg_ros.geometry import invert_transform, make_transform, yaw_of
from odg_ros.online.errors import BadInput
from odg_ros.online.poses import PoseBuffer, interpolate_pose, pose_from_xyz_xyzw, slerp
from odg_ros.online.transforms import TransformBuffer


def yaw_pose(yaw, xyz=(0, 0, 0)):
    return make_transform(Rotation.from_euler("z", yaw).as_matrix(), xyz)


def wxyz(rotation):
    x, y, z, w = rotation.as_quat()
    return np.array([w, x, y, z])


def test_slerp_hand_cases():
    q0 = np.array([1.0, 0, 0, 0])
    q90 = wxyz(Rotation.from_euler("z", 90, degrees=True))
    half = slerp(q0, q90, 0.5)
    assert np.allclose(half, wxyz(Rotation.from_euler("z", 45, degrees=True)))
    assert np.allclose(slerp(q0, q90, 0.0), q0) and np.allclose(slerp(q0, q90, 1.0), q90)
    # extrapolation continues at the same rate
    assert np.allclose(slerp(q0, q90, 1.5), wxyz(Rotation.from_euler("z", 135, degrees=True)))
    # -q is the same rotation: still the short way (to 45 deg, not 45 - 180)
    assert np.allclose(Rotation.from_quat(np.roll(slerp(q0, -q90, 0.5), -1)).as_euler("zyx")[0],
                       np.pi / 4)
    # nearly identical quaternions (the lerp branch) stay unit and exact
    q_small = wxyz(Rotation.from_euler("x", 1e-4))
    assert np.isclose(np.linalg.norm(slerp(q0, q_small, 0.3)), 1.0)
    assert np.allclose(slerp(q0, q_small, 0.3), wxyz(Rotation.from_euler("x", 3e-5)), atol=1e-9)


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
