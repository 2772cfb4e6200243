"""Hard cases of the geometry: poses (NaN, non-orthonormal, 180 degree turns, huge
translations), projection at the image border / near plane / behind the camera, time deltas
of 0, negative, epoch-sized and infinite, velocities of 0 and 100 m/s, a history of one frame.

Existing tests that already cover plain cases (not repeated here): test_motion_sampling.py
(warp against hand-computed cases, zeros behind every camera), test_online_poses.py
(pose validation at the node), test_network.py::test_fewer_frames_repeat_the_oldest.
"""
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from odg_ros import geometry
from odg_ros.network import ODG
from odg_ros.network.sampling import (DEPTH_EPS, SpatioTemporalSampling, first_visible_camera,
                                      project_to_cameras, warp_points)
from odg_ros.nuscenes_cameras import ring_ego2img

from testing.hard_cases import FEW, HARD, all_finite, log_uniform, rotation_matrix
from testing.helpers import model_inputs as random_inputs
from testing.helpers import tiny_config

unit_vectors = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3)
angles = st.floats(0.0, math.pi) | st.sampled_from([0.0, 1e-12, math.pi - 1e-9, math.pi])


# ------------------------------------------------------------------------------ geometry.py
@HARD
@given(direction=st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 1e-3),
       length=log_uniform(1e-11, 1e150))
def test_quaternion_of_any_usable_length_gives_a_rotation(direction, length):
    q = np.asarray(direction) / np.linalg.norm(direction) * length
    R = geometry.quaternion_to_matrix(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1) < 1e-12


@pytest.mark.parametrize("q", [[0, 0, 0, 0], [1e-300, 0, 0, 0], [5e-324, 0, 0, 0],
                               [math.nan, 0, 0, 1], [math.inf, 0, 0, 0], [1e308, 1e308, 0, 0]])
def test_quaternion_zero_denormal_nan_inf_is_an_error(q):
    with pytest.raises(ValueError, match="quaternion"):
        geometry.quaternion_to_matrix(q)


@HARD
@given(axis=unit_vectors, angle=angles)
def test_matrix_quaternion_round_trip_at_every_angle(axis, angle):
    R = rotation_matrix(axis, angle)          # includes 0 and exactly 180 degrees
    q = geometry.matrix_to_quaternion(R)
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[0] >= 0
    np.testing.assert_allclose(geometry.quaternion_to_matrix(q), R, atol=1e-12)


@pytest.mark.parametrize("name,R", [
    ("nan", np.full((3, 3), math.nan)),
    ("inf", np.diag([math.inf, 1.0, 1.0])),
    ("scaled", 2.0 * np.eye(3)),
    ("sheared", np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]])),
    ("reflection", np.diag([1.0, 1.0, -1.0])),
    ("zero", np.zeros((3, 3))),
])
def test_matrix_to_quaternion_rejects_what_is_not_a_rotation(name, R):
    # a NaN or a silently "nearest" quaternion of a non-rotation would pass bad poses on
    with pytest.raises(ValueError, match="rotation"):
        geometry.matrix_to_quaternion(R)


@HARD
@given(axis=unit_vectors, angle=angles, translation=st.tuples(*[st.floats(-1e7, 1e7)] * 3))
def test_invert_transform_far_from_the_origin(axis, angle, translation):
    T = geometry.make_transform(rotation_matrix(axis, angle), translation)
    inv = geometry.invert_transform(T)
    scale = 1.0 + np.abs(translation).max()
    np.testing.assert_allclose(T @ inv, np.eye(4), atol=1e-15 * scale * 8)
    np.testing.assert_allclose(geometry.ego_warp(T, T), np.eye(4), atol=1e-15 * scale * 8)
    assert geometry.is_rigid(T)


@pytest.mark.parametrize("name,T", [
    ("nan", np.where(np.eye(4) > 0, math.nan, 0.0)),
    ("inf translation", geometry.make_transform(np.eye(3), [math.inf, 0, 0])),
    ("scaled 1.01", geometry.make_transform(1.01 * np.eye(3), [0, 0, 0])),
    ("sheared", geometry.make_transform(np.array([[1, 0.01, 0], [0, 1, 0], [0, 0, 1.0]]),
                                        [0, 0, 0])),
    ("reflection", geometry.make_transform(np.diag([1.0, -1.0, 1.0]), [0, 0, 0])),
    ("bad last row", np.vstack([np.eye(4)[:3], [0, 0, 1.0, 1.0]])),
    ("3x4", np.eye(4)[:3]),
])
def test_is_rigid_rejects(name, T):
    assert not geometry.is_rigid(T)


def test_is_rigid_accepts_float32_rounding():
    R = rotation_matrix([0.3, -1, 2], 2.5).astype(np.float32).astype(np.float64)
    assert geometry.is_rigid(geometry.make_transform(R, [1e3, -2e3, 5.0]))


def test_rigid_mask_is_is_rigid_on_a_stack():
    # the node checks a set's poses and extrinsics as one stack: same verdicts, one by one,
    # on every way to fail and on both sides of the tolerance
    R = rotation_matrix([0.3, -1, 2], 2.5)
    cases = [geometry.make_transform(R, [1e3, -2e3, 5.0]),
             geometry.make_transform(R.astype(np.float32).astype(np.float64), [1, 2, 3]),
             np.where(np.eye(4) > 0, math.nan, 0.0),
             geometry.make_transform(np.eye(3), [math.inf, 0, 0]),
             geometry.make_transform(np.diag([1.0, -1.0, 1.0]), [0, 0, 0]),
             np.vstack([np.eye(4)[:3], [0, 0, 1.0, 1.0]]),
             np.vstack([np.eye(4)[:3], [0, 0, 0, 1.0 + 1e-9]])]
    for scale in (1 + 4e-4, 1 + 6e-4, 1.01):        # R R^T off by ~2 (scale - 1)
        cases.append(geometry.make_transform(scale * R, [0, 0, 0]))
    stack = np.stack(cases)
    expected = [geometry.is_rigid(T) for T in cases]
    assert True in expected and False in expected
    assert geometry.rigid_mask(stack).tolist() == expected
    assert geometry.rigid_mask(stack.reshape(2, 5, 4, 4)).ravel().tolist() == expected
    with pytest.raises(ValueError, match="4, 4"):
        geometry.rigid_mask(np.eye(4)[:3])


@HARD
@given(seed=st.integers(0, 2**32 - 1), far=st.floats(1.0, 1e7))
def test_stacked_inverses_and_ego2img_equal_the_one_matrix_functions(seed, far):
    from odg_ros.online.camera_calibration import set_ego2img
    rng = np.random.default_rng(seed)
    poses = np.stack([geometry.make_transform(q, far * rng.uniform(-1, 1, 3))
                      for q in rng.normal(size=(7, 4))])
    extrinsics = np.stack([geometry.make_transform(q, rng.uniform(-2, 2, 3))
                           for q in rng.normal(size=(6, 4))])
    intrinsics = np.stack([[[f, 0, rng.uniform(100, 600)], [0, f, rng.uniform(50, 300)],
                            [0, 0, 1]] for f in rng.uniform(50, 2000, 6)])
    inverses = geometry.invert_transforms(poses)
    assert all(np.array_equal(inverses[i], geometry.invert_transform(T))
               for i, T in enumerate(poses))                              # bit for bit
    one_by_one = np.stack([geometry.ego_to_image(K, S) @ (geometry.invert_transform(P)
                                                          @ poses[0])
                           for K, S, P in zip(intrinsics, extrinsics, poses[1:])])
    assert np.array_equal(set_ego2img(intrinsics, extrinsics, poses[1:], poses[0]), one_by_one)
    poses[4, :3, :3] *= 1.01
    with pytest.raises(ValueError, match=r"transform \(4,\) is not rigid"):
        geometry.invert_transforms(poses)


@pytest.mark.parametrize("name,T", [
    ("nan", np.full((4, 4), math.nan)),
    ("non-orthonormal", geometry.make_transform(2.0 * np.eye(3), [1.0, 2.0, 3.0])),
])
def test_invert_transform_rejects_what_it_cannot_invert(name, T):
    # R^T is the inverse only of an orthonormal R: anything else would be silently wrong
    with pytest.raises(ValueError, match="rigid"):
        geometry.invert_transform(T)


# ------------------------------------------------------------------------------ projection
def pinhole(fx=100.0, cx=50.0, cy=25.0):
    """ego2img [1, 1, 1, 4, 4] float64 of a camera at the ego origin with camera axes =
    ego axes (z forward), image 100 x 50 (W x H). Pixel u = (fx x + cx z) / z exactly."""
    e2i = torch.eye(4, dtype=torch.float64)
    e2i[0, 0], e2i[1, 1], e2i[0, 2], e2i[1, 2] = fx, fx, cx, cy
    return e2i.view(1, 1, 1, 4, 4)


@pytest.mark.parametrize("point,visible,uv", [
    ((-1.0, 0.0, 2.0), True, (0.0, 25.0)),          # u == 0 exactly: first column, inside
    ((1.0, 0.0, 2.0), False, None),                 # u == W exactly: outside (half-open)
    ((0.0, -0.5, 2.0), True, (50.0, 0.0)),          # v == 0
    ((0.0, 0.5, 2.0), False, None),                 # v == H
    ((0.0, 0.0, DEPTH_EPS), False, None),           # on the near plane: culled
    ((0.0, 0.0, 2 * DEPTH_EPS), True, (50.0, 25.0)),  # just in front of it
    ((0.0, 0.0, 0.0), False, None),                 # at the camera centre
    ((0.0, 0.0, -3.0), False, None),                # behind
    ((1e-3, 1e-3, -1e-9), False, None),             # just behind: no sign flip into view
    ((math.nan, 0.0, 2.0), False, None),
    ((math.inf, 0.0, 2.0), False, None),
    ((0.0, 0.0, math.inf), False, None),
])
def test_projection_at_border_near_plane_and_behind(point, visible, uv):
    pts = torch.tensor(point, dtype=torch.float64).view(1, 1, 1, 1, 3)
    u, v, camera, vis = first_visible_camera(pts, pinhole(), (50, 100))
    assert bool(vis) == visible
    if visible:
        assert (float(u), float(v)) == uv
    grid, _ = project_to_cameras(pts, pinhole(), (50, 100))
    assert torch.isfinite(grid).all()


def sampler(seed=0, dims=32, groups=4, points=2, levels=2, dtype=torch.float64):
    torch.manual_seed(seed)
    module = SpatioTemporalSampling(dims, groups, points, levels).to(dtype)
    torch.nn.init.normal_(module.offsets.weight, std=0.1)   # let the query move the points
    return module


def sample(module, B=1, Q=7, K=3, T=3, dt=None, velocity=None, warp=None, e2i=None,
           dtype=torch.float64):
    """Run the sampler on a ring rig over random features -> (sampled, inputs)."""
    g = torch.Generator().manual_seed(1)
    H, W = 32, 88
    G, L = module.num_groups, module.num_levels
    c = module.offsets.in_features // G
    query = torch.randn(B, Q, G * c, generator=g, dtype=dtype, requires_grad=True)
    means = (torch.rand(B, Q, K, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor(
        [60.0, 60.0, 4.0], dtype=dtype)
    feats = [torch.randn(T * B * G, c, 6, H // 4 >> l, W // 4 >> l, generator=g, dtype=dtype)
             for l in range(L)]
    e2i = ring_ego2img((H, W), T, 6, B).to(dtype) if e2i is None else e2i
    warp = torch.eye(4, dtype=dtype).repeat(B, T, 1, 1) if warp is None else warp
    dt = torch.arange(T, dtype=dtype).repeat(B, 1) * 0.5 if dt is None else dt
    out = module(query, means, velocity, feats, e2i, warp, dt, (H, W))
    return out, query


TIME_DELTAS = [0.0, -0.5, 1e-9, 0.5, 3600.0, 1.7e9, -1.7e9]


@HARD
@given(dt=st.lists(st.sampled_from(TIME_DELTAS) | st.floats(-1e10, 1e10), min_size=3,
                   max_size=3),
       speed=st.sampled_from([0.0, 1e-6, 100.0, -100.0]) | st.floats(-100, 100),
       heading=st.floats(-math.pi, math.pi))
def test_velocity_warp_is_exact_for_any_time_delta_and_speed(dt, speed, heading):
    x0 = torch.tensor([[[[5.0, -3.0, 1.0], [0.0, 0.0, 0.0]]]], dtype=torch.float64)
    v = torch.tensor([[[speed * math.cos(heading), speed * math.sin(heading)]]],
                     dtype=torch.float64)
    dts = torch.tensor([dt], dtype=torch.float64)
    out = warp_points(x0, v, dts, None)[0, 0]                    # [T, M, 3]
    assert torch.isfinite(out).all()
    expected_xy = x0[0, 0, None, :, :2] - v[0, 0] * dts[0, :, None, None]
    torch.testing.assert_close(out[..., :2], expected_xy, rtol=1e-15, atol=0)
    assert torch.equal(out[..., 2], x0[0, 0, None, :, 2].expand(3, 2))     # z never moves


@FEW
@given(dt=st.lists(st.sampled_from(TIME_DELTAS) | st.floats(-1e10, 1e10), min_size=3,
                   max_size=3),
       speed=st.sampled_from([0.0, 100.0]))
def test_sampling_finite_with_finite_gradients_for_extreme_time_and_speed(dt, speed):
    module = sampler()
    velocity = torch.full((1, 7, 2), speed, dtype=torch.float64, requires_grad=True)
    out, query = sample(module, dt=torch.tensor([dt], dtype=torch.float64), velocity=velocity)
    assert torch.isfinite(out).all()
    grads = torch.autograd.grad(out.square().sum(), [query, velocity, *module.parameters()])
    assert all_finite(*grads)


def test_far_points_project_onto_the_horizon_not_to_nan():
    # 1.7e9 s at 100 m/s (an epoch stamp against 0 after a bag restart): 2.4e11 m away.
    # The ring sees all around, so such a point is still in view, on the horizon row of the
    # 1.5 m high horizontal cameras (v -> cy = H / 2), with a finite read.
    points = torch.tensor([[5.0, -3.0, 1.0]], dtype=torch.float64).view(1, 1, 1, 3)
    velocity = torch.tensor([[[100.0, 100.0]]], dtype=torch.float64)
    dt = torch.tensor([[0.0, 1.7e9, -1.7e9]], dtype=torch.float64)
    warped = warp_points(points, velocity, dt, None)
    e2i = ring_ego2img((32, 88), 3, 6, 1).double()
    u, v, camera, visible = first_visible_camera(warped, e2i, (32, 88))
    assert visible.all() and torch.isfinite(u).all()
    torch.testing.assert_close(v[0, 1:], torch.full_like(v[0, 1:], 16.0), atol=1e-6, rtol=0)
    module = sampler()
    out, _ = sample(module, dt=dt, velocity=torch.full((1, 7, 2), 100.0, dtype=torch.float64))
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("case", ["nan warp", "inf warp", "non-orthonormal warp",
                                  "nan ego2img", "zero ego2img", "singular ego2img",
                                  "inf time delta", "nan time delta"])
def test_sampling_with_corrupt_geometry_gives_finite_features(case):
    """Non-finite geometry is rejected where it enters (dataset and node: is_rigid, finite
    stamps; test_online_poses.py, test_dataset.py). Should one reach the network anyway,
    the frame / camera reads zeros (a NaN point is in no camera), never NaN features; its
    gradient is NaN, so the trainer skips such a step (test_hard_training.py)."""
    module = sampler()
    warp = torch.eye(4, dtype=torch.float64).repeat(1, 3, 1, 1)
    e2i = ring_ego2img((32, 88), 3, 6, 1).double()
    dt = torch.tensor([[0.0, 0.5, 1.0]], dtype=torch.float64)
    if case == "nan warp":
        warp[0, 1] = math.nan
    elif case == "inf warp":
        warp[0, 1, :3, 3] = math.inf
    elif case == "non-orthonormal warp":
        warp[0, 1, :3, :3] *= 3.0
    elif case == "nan ego2img":
        e2i[0, 2] = math.nan                       # every camera of frame 2
    elif case == "zero ego2img":
        e2i[0, 2] = 0.0
    elif case == "singular ego2img":
        e2i[0, 2, :, :, 2] = 0.0                   # rank 3: blind to height, still finite
    elif case == "inf time delta":
        dt[0, 2] = math.inf
    elif case == "nan time delta":
        dt[0, 2] = math.nan
    velocity = torch.full((1, 7, 2), 10.0, dtype=torch.float64)
    out, query = sample(module, warp=warp, e2i=e2i, dt=dt, velocity=velocity)
    assert torch.isfinite(out).all()
    P = module.num_points
    if case in ("nan warp", "inf warp"):
        assert out[:, :, :, P:2 * P].abs().max() == 0           # frame 1 reads nothing
    if case in ("inf time delta", "nan time delta"):
        assert out[:, :, :, 2 * P:].abs().max() == 0           # frame 2 reads nothing
    if case in ("zero ego2img", "nan ego2img"):
        assert out[:, :, :, 2 * P:].abs().max() == 0           # frame 2 has no camera


# ------------------------------------------------------------------------------ whole model
def model_inputs(cfg, frames, dt=None):
    images, e2i, warp, ring_dt = random_inputs(cfg, frames)
    return images, e2i, warp, ring_dt if dt is None else dt


@pytest.fixture(scope="module")
def tiny_model():
    torch.manual_seed(0)
    cfg = tiny_config(image_size=(32, 88))
    return cfg, ODG(cfg)


def check_output_and_gradients(model, out):
    tensors = [out.init_means]
    for layer in out.layers:
        tensors += [layer.means, layer.logits, layer.scales, layer.rotations, layer.opacities,
                    layer.boxes, layer.box_logits]
    assert all_finite(*tensors)
    loss = sum(t.float().square().mean() for t in tensors if t is not None)
    model.zero_grad(set_to_none=True)
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all_finite(*grads)


def test_history_of_one_frame_trains(tiny_model):
    cfg, model = tiny_model
    model.train()
    out = model(*model_inputs(cfg, 1), gaussian_attributes=True)
    check_output_and_gradients(model, out)


@pytest.mark.parametrize("dt", [[0.0, 0.0, 0.0], [0.0, -0.5, -1.0], [0.0, 1.7e9, 3.4e9]])
def test_model_with_100_mps_objects_and_odd_time_deltas(tiny_model, dt):
    cfg, model = tiny_model
    model.train()
    with torch.no_grad():
        saved = model.queries.init_box.clone()
        model.queries.init_box[:, 5:7] = 100.0 / math.sqrt(2)     # |v| = 100 m/s
    try:
        out = model(*model_inputs(cfg, 3, torch.tensor([dt])), gaussian_attributes=True)
        check_output_and_gradients(model, out)
    finally:
        with torch.no_grad():
            model.queries.init_box.copy_(saved)
