"""4D sampling: motion compensation against hand-computed cases, sampling against a float64
reference, hard cases (points behind / outside every camera)."""
import math

import numpy as np
import torch

from odg_ros.geometry import ego_to_image, ego_warp, make_transform
from odg_ros.network.sampling import (SpatioTemporalSampling, project_to_cameras,
                                      warp_points)
from odg_ros.nuscenes_cameras import ring_cameras

HW = (64, 176)


def project_np(ego2img, p):
    q = ego2img @ np.append(p, 1.0)
    return q[:2] / q[2], q[2]


def random_pose(rng):
    yaw = rng.uniform(-math.pi, math.pi)
    R = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    return make_transform(R, rng.uniform(-100, 100, 3))


def test_static_point_projects_like_a_direct_projection_with_the_past_pose():
    rng = np.random.default_rng(0)
    K, T_ego_cam = ring_cameras(HW)
    e2i = ego_to_image(K[0], T_ego_cam[0])
    for _ in range(20):
        P0, P1 = random_pose(rng), random_pose(rng)
        # a world point 10 m in front of the PAST ego, so the front camera saw it then
        X = P1 @ np.array([10.0, rng.uniform(-2, 2), rng.uniform(0, 2), 1.0])
        p0 = (np.linalg.inv(P0) @ X)[:3]                                  # current ego frame
        direct_uv, _ = project_np(e2i, (np.linalg.inv(P1) @ X)[:3])
        warped = warp_points(torch.tensor(p0).view(1, 1, 1, 3), None,
                             torch.tensor([[0.0, 0.5]], dtype=torch.float64),
                             torch.from_numpy(np.stack([np.eye(4), ego_warp(P0, P1)]))[None])
        uv, _ = project_np(e2i, warped[0, 0, 1, 0].numpy())
        np.testing.assert_allclose(uv, direct_uv, atol=1e-6)
        np.testing.assert_allclose(warped[0, 0, 0, 0].numpy(), p0)  # frame 0 untouched


def test_velocity_warp_moves_point_back_along_velocity():
    x0 = torch.tensor([[[[5.0, -3.0, 1.0]]]], dtype=torch.float64)
    v = torch.tensor([[[4.0, -2.0]]], dtype=torch.float64)
    dt = torch.tensor([[0.0, 0.5, 1.5]], dtype=torch.float64)
    out = warp_points(x0, v, dt, None)[0, 0, :, 0]
    expected = torch.tensor([[5.0, -3.0, 1.0], [3.0, -2.0, 1.0], [-1.0, 0.0, 1.0]],
                            dtype=torch.float64)
    torch.testing.assert_close(out, expected)  # x - v dt, z unchanged


def test_zero_velocity_or_zero_dt_change_nothing():
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(2, 5, 4, 3, generator=g, dtype=torch.float64)
    v = torch.randn(2, 5, 2, generator=g, dtype=torch.float64)
    dt = torch.rand(2, 3, generator=g, dtype=torch.float64)
    base = warp_points(x0, None, dt, None)
    torch.testing.assert_close(warp_points(x0, torch.zeros_like(v), dt, None), base)
    torch.testing.assert_close(warp_points(x0, v, torch.zeros_like(dt), None), base)


def bilinear_reference(feat, u, v, H, W):
    """float64 bilinear read of feat [C, h, w] at image pixel (u, v), zero padding,
    align_corners=False (pixel centres at +0.5)."""
    C, h, w = feat.shape
    x = u / W * w - 0.5
    y = v / H * h - 0.5
    x0, y0 = math.floor(x), math.floor(y)
    out = np.zeros(C)
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            wgt = (1 - abs(x - xi)) * (1 - abs(y - yi))
            if 0 <= xi < w and 0 <= yi < h:
                out += wgt * feat[:, yi, xi]
    return out


def test_sampling_matches_float64_reference_on_random_inputs():
    rng = np.random.default_rng(3)
    torch.manual_seed(3)
    B, Q, T, N, G, P, c, L = 2, 7, 2, 6, 2, 3, 3, 2
    K, T_ego_cam = ring_cameras(HW)
    e2i = np.stack([ego_to_image(k, t) for k, t in zip(K, T_ego_cam)])
    ego2img = torch.from_numpy(np.broadcast_to(e2i, (B, T, N, 4, 4)).copy()).float()
    warp = torch.eye(4).repeat(B, T, 1, 1)
    warp[:, 1, :3, 3] = torch.tensor([3.0, -1.0, 0.0])
    dt = torch.tensor([[0.0, 0.5]] * B)
    shapes = [(16, 44), (8, 22)]
    feats_np = [rng.normal(size=(T, B, G, c, N, h, w)) for h, w in shapes]
    mlvl = [torch.from_numpy(f.reshape(T * B * G, c, N, *f.shape[-2:])).float() for f in feats_np]
    sampler = SpatioTemporalSampling(G * c, G, P, L)
    with torch.no_grad():
        sampler.offsets.weight.normal_(0, 0.3)
        sampler.level_weights.weight.normal_(0, 0.3)
    query = torch.randn(B, Q, G * c)
    prev = torch.from_numpy(rng.uniform([-30, -30, -1], [30, 30, 3], size=(B, Q, 4, 3))).float()
    velocity = torch.randn(B, Q, 2) * 5
    with torch.no_grad():
        out = sampler(query, prev, velocity, mlvl, ego2img, warp, dt, HW).double().numpy()
        offsets = sampler.offsets(query).view(B, Q, G * P, 3).double().numpy()
        weights = sampler.level_weights(query).view(B, Q, G, P, L).softmax(-1).double().numpy()
    prev64 = prev.double().numpy()
    checked = visible_count = 0
    for b in range(B):
        for q in range(Q):
            centre = prev64[b, q].mean(0)
            spread = prev64[b, q].std(0, ddof=1)
            for t in range(T):
                for g in range(G):
                    for p in range(P):
                        x = centre + offsets[b, q, g * P + p] * spread
                        x[:2] -= velocity[b, q].double().numpy() * dt[b, t].item()
                        x = (warp[b, t].double().numpy() @ np.append(x, 1))[:3]
                        expected = np.zeros(c)
                        for n in range(N):
                            (u, v_), d = project_np(e2i[n], x)
                            if d > 1e-5 and 0 <= u < HW[1] and 0 <= v_ < HW[0]:
                                for lvl in range(L):
                                    expected += weights[b, q, g, p, lvl] * bilinear_reference(
                                        feats_np[lvl][t, b, g, :, n], u, v_, *HW)
                                visible_count += 1
                                break
                        np.testing.assert_allclose(out[b, q, g, t * P + p], expected,
                                                   atol=1e-4)
                        checked += 1
    assert visible_count > checked // 2  # most points land in some camera


def test_points_behind_or_outside_every_camera_give_zeros_not_nan():
    K, T_ego_cam = ring_cameras(HW)
    e2i = torch.from_numpy(np.stack([ego_to_image(k, t) for k, t in zip(K, T_ego_cam)])).float()
    # straight above, at a camera centre (depth 0), far below, 45 degrees up: outside every view
    pts = torch.tensor([[0.0, 0.0, 200.0], [1.0, 0.0, 1.5], [0.0, 0.0, -1e6], [1e4, 0, 1e4]])
    grid, visible = project_to_cameras(pts.view(1, 4, 1, 1, 3), e2i.view(1, 1, 6, 4, 4), HW)
    assert not visible.any()
    assert torch.isfinite(grid).all()
    sampler = SpatioTemporalSampling(8, 2, 2, 1)
    feat = [torch.ones(2, 4, 6, 8, 22)]
    out = sampler(torch.zeros(1, 4, 8), pts.view(1, 4, 1, 3), None, feat,
                  e2i.view(1, 1, 6, 4, 4), None, torch.zeros(1, 1), HW)
    assert torch.equal(out, torch.zeros_like(out))


def test_dynamic_object_is_found_in_the_past_frame_only_with_its_velocity():
    """Frame -1's features are non-zero only where the object WAS; a dynamic query at the
    object's current position reads them only when it warps by its velocity."""
    K, T_ego_cam = ring_cameras(HW)
    e2i = torch.from_numpy(np.stack([ego_to_image(k, t) for k, t in zip(K, T_ego_cam)])).float()
    x_now, v, dt = np.array([15.0, 0.0, 1.0]), np.array([8.0, 0.0]), 1.0
    x_then = x_now.copy()
    x_then[:2] -= v * dt
    (u, v_pix), _ = project_np(e2i[0].double().numpy(), x_then)
    (u_now, _), _ = project_np(e2i[0].double().numpy(), x_now)
    assert abs(u - u_now) < 1  # same column (straight ahead) -> check rows differ
    feat = torch.zeros(2, 1, 1, 6, HW[0], HW[1])  # T=2, B=1, G=1, c=1, full resolution
    feat[1, 0, 0, 0, int(v_pix), int(u)] = 1.0
    mlvl = [feat.view(2, 1, 6, HW[0], HW[1])]
    sampler = SpatioTemporalSampling(4, 1, 1, 1)
    prev = torch.tensor(x_now, dtype=torch.float32).view(1, 1, 1, 3)
    ego2img = e2i.expand(1, 2, 6, 4, 4)
    dts = torch.tensor([[0.0, dt]])
    with torch.no_grad():
        with_v = sampler(torch.zeros(1, 1, 4), prev, torch.from_numpy(v).float().view(1, 1, 2),
                         mlvl, ego2img, None, dts, HW)
        without_v = sampler(torch.zeros(1, 1, 4), prev, None, mlvl, ego2img, None, dts, HW)
    assert with_v[0, 0, 0, 1, 0] > 0.2      # frame -1 read at the object's past position
    assert without_v[0, 0, 0, 1, 0] == 0    # ego-only compensation misses it
