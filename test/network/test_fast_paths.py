"""Fast paths against the plain path they replace: each must give the same numbers.

- camera-rows sampling (2-D grid_sample over the cameras stacked along the rows, a zero row
  between them) vs the plain per-camera 3-D grid_sample: equal within 1e-10 in float64 (the
  formulations are the same bilinear read; only the normalised-coordinate round trip differs)
  and within 2e-5 in float32, at image borders too;
- ``ODG.decode`` (camera rows) vs the plain layout: equal within 1e-3 after six random layers
  (float32 rounding of the grid, amplified by random weights);
- ``ODG.decode_ring`` over a ``FeatureRing`` vs ``ODG.decode`` over the list: equal within
  1e-6 (the same kernels on the same numbers, the frames in another storage order).
"""
import numpy as np
import pytest
import torch

from odg_ros.geometry import ego_to_image
from odg_ros.network import ODG
from odg_ros.network.budget import budget_ladder
from odg_ros.network.feature_ring import FeatureRing
from odg_ros.network.sampling import SpatioTemporalSampling, camera_rows_layout
from odg_ros.nuscenes_cameras import ring_cameras

from testing.helpers import model_inputs, tiny_config

HW = (64, 176)


def ring_e2i(B, T, dtype):
    K, T_ego_cam = ring_cameras(HW)
    e2i = np.stack([ego_to_image(k, t) for k, t in zip(K, T_ego_cam)])
    return torch.from_numpy(np.broadcast_to(e2i, (B, T, 6, 4, 4)).copy()).to(dtype)


def sampler_and_inputs(dtype, border: bool, seed=0):
    """A sampler with random offsets, and queries whose points land anywhere in the views or
    (border) within half a feature pixel of an image border."""
    g = torch.Generator().manual_seed(seed)
    B, Q, T, G, P, c, L = 2, 40, 3, 2, 3, 4, 3
    sampler = SpatioTemporalSampling(G * c, G, P, L).to(dtype)
    with torch.no_grad():
        sampler.offsets.weight.normal_(0, 0.3, generator=g)
        sampler.level_weights.weight.normal_(0, 0.3, generator=g)
    e2i = ring_e2i(B, T, dtype)
    warp = torch.eye(4, dtype=dtype).repeat(B, T, 1, 1)
    warp[:, 1, :3, 3] = torch.tensor([3.0, -1.0, 0.0])
    warp[:, 2, :3, 3] = torch.tensor([6.0, 0.5, 0.0])
    dt = torch.tensor([[0.0, 0.5, 1.0]] * B, dtype=dtype)
    if border:
        # single-mean queries sample at their centre: put centres on rays through the
        # borders of the front camera (and just inside / outside them)
        inv = torch.linalg.inv(e2i[0, 0, 0].double())          # front camera
        u = torch.tensor([0.0, 0.3, HW[1] - 0.3, HW[1] - 1e-3, 50.0, 100.0, 20.0, 170.0])
        v = torch.tensor([30.0, 10.0, 40.0, 20.0, 0.0, 0.2, HW[0] - 0.2, HW[0] - 1e-3])
        depth = 5.0 + 20.0 * torch.rand(Q, generator=g)
        uu, vv = u.repeat(Q // len(u)), v.repeat(Q // len(v))
        pix = torch.stack([uu * depth, vv * depth, depth, torch.ones(Q)], 1).double()
        prev = (pix @ inv.T)[:, :3].to(dtype).view(1, Q, 1, 3).repeat(B, 1, 1, 1)
        with torch.no_grad():
            sampler.offsets.weight.zero_()   # points exactly at the centres
    else:
        prev = torch.rand(B, Q, 4, 3, generator=g, dtype=dtype) * 60 - 30
        prev[..., 2] = prev[..., 2] / 10 + 1.0
    query = torch.randn(B, Q, G * c, generator=g, dtype=dtype)
    velocity = torch.randn(B, Q, 2, generator=g, dtype=dtype) * 3
    levels = [torch.randn(B * T, 6, G * c, h, w, generator=g, dtype=dtype)
              for h, w in ((16, 44), (8, 22), (4, 11))]
    frames = [[f.view(T, B, 6, G * c, *f.shape[-2:])[t] for f in levels] for t in range(T)]
    return sampler, query, prev, velocity, frames, e2i, warp, dt


def plain_layout(frames, G):
    """The plain layout [T*B*G, c, N, h, w] of T frames of L levels [B, N, C, h, w]."""
    out = []
    for level in range(len(frames[0])):
        stacked = torch.stack([f[level].unflatten(2, (G, -1)).permute(0, 2, 3, 1, 4, 5)
                               for f in frames])
        out.append(stacked.reshape(-1, *stacked.shape[3:]))
    return out


@pytest.mark.parametrize("dtype,atol", [(torch.float64, 1e-10), (torch.float32, 2e-5)])
@pytest.mark.parametrize("border", [False, True])
def test_camera_rows_sampling_equals_the_per_camera_3d_sampling(dtype, atol, border):
    sampler, query, prev, velocity, frames, e2i, warp, dt = sampler_and_inputs(dtype, border)
    G = sampler.num_groups
    with torch.no_grad():
        plain = sampler(query, prev, velocity, plain_layout(frames, G), e2i, warp, dt, HW)
        rows = sampler(query, prev, velocity,
                       [camera_rows_layout([f[lv] for f in frames], G) for lv in range(3)],
                       e2i, warp, dt, HW)
    assert plain.abs().sum() > 0 and (plain != 0).float().mean() > 0.3
    torch.testing.assert_close(rows, plain, rtol=0, atol=atol)


def test_camera_rows_border_reads_fall_off_to_zero_like_zero_padding():
    """A constant feature map: inside a camera the read is 1; within half a feature pixel of
    the top / bottom border the bilinear weight leaks to the zero row, exactly as the
    zero padding of the per-camera read (a neighbouring camera's rows would give 1)."""
    sampler, query, prev, velocity, frames, e2i, warp, dt = sampler_and_inputs(
        torch.float64, border=True)
    frames = [[torch.ones_like(f) for f in frame] for frame in frames]
    G = sampler.num_groups
    with torch.no_grad():
        sampler.level_weights.weight.zero_()
        plain = sampler(query, prev, None, plain_layout(frames, G), e2i, None, dt * 0, HW)
        rows = sampler(query, prev, None,
                       [camera_rows_layout([f[lv] for f in frames], G) for lv in range(3)],
                       e2i, None, dt * 0, HW)
    torch.testing.assert_close(rows, plain, rtol=0, atol=1e-10)
    values = rows[..., 0].flatten()
    assert (values < 0.999).any() and (values > 0.999).any()   # some reads touch a border


def test_camera_rows_sampling_gradients_equal_the_plain_ones():
    sampler, query, prev, velocity, frames, e2i, warp, dt = sampler_and_inputs(
        torch.float64, border=False, seed=1)
    G = sampler.num_groups
    grads = []
    for layout in ("plain", "rows"):
        leaves = [[f.detach().clone().requires_grad_() for f in frame] for frame in frames]
        q = query.detach().clone().requires_grad_()
        mlvl = plain_layout(leaves, G) if layout == "plain" else \
            [camera_rows_layout([f[lv] for f in leaves], G) for lv in range(3)]
        out = sampler(q, prev, velocity, mlvl, e2i, warp, dt, HW)
        (out * torch.linspace(-1, 1, out.shape[-1], dtype=out.dtype)).sum().backward()
        grads.append([q.grad] + [f.grad for frame in leaves for f in frame])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-9)


def test_frame_index_reads_stored_frames_in_time_order():
    sampler, query, prev, velocity, frames, e2i, warp, dt = sampler_and_inputs(torch.float64,
                                                                               False)
    G = sampler.num_groups
    order = [2, 0, 1]                       # storage slot s holds time step order[s]
    stored = [frames[t] for t in order]
    index = torch.tensor([order.index(t) for t in range(3)] + [order.index(2)])  # + padding
    with torch.no_grad():
        expected = sampler(query, prev, velocity, plain_layout(frames + [frames[2]], G),
                           torch.cat([e2i, e2i[:, 2:]], 1), torch.cat([warp, warp[:, 2:]], 1),
                           torch.cat([dt, dt[:, 2:]], 1), HW)
        got = sampler(query, prev, velocity,
                      [camera_rows_layout([f[lv] for f in stored], G) for lv in range(3)],
                      e2i[:, order], warp[:, order], dt[:, order], HW, frame_index=index)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-10)


def assert_outputs_close(a, b, tol):
    for x, y in zip(a.layers, b.layers):
        torch.testing.assert_close(x.means, y.means, rtol=tol, atol=tol)
        torch.testing.assert_close(x.logits, y.logits, rtol=tol, atol=tol)
        torch.testing.assert_close(x.boxes, y.boxes, rtol=tol, atol=tol)


@pytest.mark.parametrize("frames,budget", [(3, False), (2, False), (3, True)])
def test_model_decode_fast_layout_equals_plain_layout(frames, budget):
    torch.manual_seed(0)
    cfg = tiny_config(num_frames=3, image_size=(32, 88))
    model = ODG(cfg).eval()
    images, e2i, warp, dt = model_inputs(cfg, frames)
    chosen = None
    if budget:   # the layers after the budget's refine fewer queries than the model has
        model.decoder.budget_heads.set_trained(True)
        chosen = budget_ladder(cfg)[-1]
    with torch.no_grad():
        fast = model(images, e2i, warp, dt, budget=chosen)
        model.fast_sampling = False
        plain = model(images, e2i, warp, dt, budget=chosen)
    assert_outputs_close(fast, plain, 1e-3)
    if budget:
        kept = fast.layers[-2].query_index
        assert 0 < kept.shape[1] < cfg.num_queries and torch.equal(
            kept, plain.layers[-2].query_index)


def test_decode_ring_equals_decode_over_the_cached_list_while_streaming():
    torch.manual_seed(0)
    cfg = tiny_config(num_frames=3, image_size=(32, 88))
    model = ODG(cfg).eval()
    stream = torch.randn(6, 1, cfg.num_cams, 3, *cfg.image_size)
    _, e2i, warp, dt = model_inputs(cfg, 3)
    ring, cache = FeatureRing(3, cfg.num_groups), []
    with torch.no_grad():
        for t in range(6):                # 1, 2 frames (filling up), then full and wrapping
            feats = model.extract_features(stream[t])
            ring.push(feats)
            cache = ([feats] + cache)[:3]
            T = len(cache)
            assert len(ring) == T
            got = model.decode_ring(ring, e2i[:, :T], warp[:, :T], dt[:, :T])
            expected = model.decode(cache, e2i[:, :T], warp[:, :T], dt[:, :T])
            assert_outputs_close(got, expected, 1e-6)
        ring.clear()
        assert len(ring) == 0
        ring.push(feats)
        assert_outputs_close(model.decode_ring(ring, e2i[:, :1], warp[:, :1], dt[:, :1]),
                             model.decode([feats], e2i[:, :1], warp[:, :1], dt[:, :1]), 1e-6)


def test_feature_ring_rejects_bad_input_clearly():
    cfg = tiny_config(num_frames=2, image_size=(32, 88))
    model = ODG(cfg).eval()
    ring = FeatureRing(2, cfg.num_groups)
    _, e2i, warp, dt = model_inputs(cfg, 2)
    with pytest.raises(ValueError, match="empty"):
        model.decode_ring(ring, e2i[:, :1], warp[:, :1], dt[:, :1])
    with torch.no_grad():
        feats = model.extract_features(torch.randn(1, cfg.num_cams, 3, *cfg.image_size))
    ring.push(feats)
    with pytest.raises(ValueError, match="geometry"):
        model.decode_ring(ring, e2i, warp, dt)
    with pytest.raises(ValueError, match="differ"):
        ring.push([f[..., :-1] for f in feats])
    with pytest.raises(ValueError):
        FeatureRing(0, 4)


def test_half_precision_features_are_laid_out_in_float32_exactly():
    """A bf16 grid over N*(h+1) stacked rows would put points up to ~0.4 px off; the layout
    (and the ring) keep float32, which holds every bf16 value exactly."""
    g = torch.Generator().manual_seed(0)
    frames = [[torch.randn(1, 6, 8, 4, 11, generator=g).bfloat16()] for _ in range(2)]
    rows = camera_rows_layout([f[0] for f in frames], 2)
    assert rows.dtype == torch.float32
    back = rows.permute(0, 2, 3, 1).reshape(2, 1, 2, 6, 5, 11, 4)[:, :, :, :, 1:]
    expected = torch.stack([f[0].float().view(1, 6, 2, 4, 4, 11).permute(0, 2, 1, 3, 4, 5)
                            .permute(0, 1, 2, 4, 5, 3) for f in frames])
    assert torch.equal(back, expected)
    ring = FeatureRing(2, 2)
    ring.push([f.float() for f in frames[0]])          # float32 first, then bf16: one ring
    ring.push(frames[1])
    assert ring.levels()[0].dtype == torch.float32
    assert torch.equal(ring.levels()[0], rows)
