"""Gaussian splatting renderer (odg_ros.render) against a brute-force float64 reference."""

import numpy as np
import pytest
import torch

from odg_ros.render import RenderResult, render_cameras, render_gaussians, render_scenes
from odg_ros.render import splat as splat_module
from odg_ros.render.splat import _PairWeightedSum, _TileGrid
from testing.render import HW, K, NEAR, random_scene, reference_render


def render(scene, cam_from_ego, intrinsics, pixels, **kw):
    return render_gaussians(scene["means"], scene["scales"], scene["rotations"],
                            scene["opacities"], scene["features"], cam_from_ego, intrinsics,
                            pixels, HW, **kw)


def reference(scene, cam_from_ego, intrinsics, pixels, dtype=np.float64):
    return reference_render(*(scene[k].detach().numpy() for k in
                              ("means", "scales", "rotations", "opacities", "features")),
                            cam_from_ego.numpy(), intrinsics.numpy(), pixels.numpy(), HW,
                            dtype=dtype)


def assert_matches_reference(result, expected, atol=1e-9, rtol=1e-9):
    depth, features, alpha = expected
    np.testing.assert_allclose(result.depth.detach().numpy(), depth, atol=atol, rtol=rtol)
    np.testing.assert_allclose(result.features.detach().numpy(), features, atol=atol, rtol=rtol)
    np.testing.assert_allclose(result.alpha.detach().numpy(), alpha, atol=atol, rtol=rtol)


def backward_grads(scene, cam_from_ego, intrinsics, pixels):
    """Gradients of a loss over all outputs w.r.t. every Gaussian tensor (None if unused)."""
    scene = {n: t.detach().clone().requires_grad_(True) for n, t in scene.items()}
    result = render(scene, cam_from_ego, intrinsics, pixels)
    loss = result.depth.sum() + result.features.square().sum() + result.alpha.sum()
    grads = torch.autograd.grad(loss, list(scene.values()), allow_unused=True)
    return dict(zip(scene.keys(), grads))


def simple_scene(means_cam, scales, opacities=None, rotations=None, features=None):
    """Gaussians given directly in the camera frame (camera = ego)."""
    g = len(means_cam)
    scene = dict(
        means=torch.tensor(means_cam, dtype=torch.float64).reshape(g, 3),
        scales=torch.tensor(scales, dtype=torch.float64).reshape(g, 3),
        rotations=(torch.tensor(rotations, dtype=torch.float64).reshape(g, 4)
                   if rotations is not None else torch.tensor([[1.0, 0, 0, 0]] * g,
                                                              dtype=torch.float64).reshape(g, 4)),
        opacities=(torch.tensor(opacities, dtype=torch.float64).reshape(g)
                   if opacities is not None else torch.full((g,), 0.8, dtype=torch.float64)),
        features=(torch.tensor(features, dtype=torch.float64).reshape(g, -1)
                  if features is not None else torch.rand(g, 3, dtype=torch.float64)),
    )
    return scene, torch.eye(4, dtype=torch.float64), torch.tensor(K, dtype=torch.float64)


def grid_pixels(step=8):
    v, u = torch.meshgrid(torch.arange(0, HW[0], step) + 0.5, torch.arange(0, HW[1], step) + 0.5,
                          indexing="ij")
    return torch.stack([u.flatten(), v.flatten()], dim=-1).double()


# ----------------------------------------------------------------------------- values
@pytest.mark.parametrize("seed,num_gaussians,num_pixels,dense",
                         [(0, 1, 64, False), (1, 30, 200, False), (2, 200, 300, False),
                          (3, 600, 150, False), (4, 5, 400, False), (9, 500, 200, True)])
def test_matches_bruteforce_reference(seed, num_gaussians, num_pixels, dense):
    scene, cam, k, pixels = random_scene(seed, num_gaussians, num_pixels, dense=dense)
    result = render(scene, cam, k, pixels)
    assert_matches_reference(result, reference(scene, cam, k, pixels))
    if dense:  # the early stop is exercised
        assert (result.alpha > 1 - 1e-3).float().mean() > 0.5


def test_float32_close_to_float64_reference():
    scene, cam, k, pixels = random_scene(7, 300, 300, dtype=torch.float32)
    result = render(scene, cam, k, pixels)
    expected = reference_render(*(scene[n].numpy() for n in scene), cam.numpy(), k.numpy(),
                                pixels.numpy(), HW)
    assert_matches_reference(result, expected, atol=2e-4, rtol=1e-4)


def test_closed_form_single_gaussian():
    # Isotropic Gaussian on the optical axis: sigma_px = f s / z, alpha = o exp(-r^2 / 2 var).
    z, s, o = 10.0, 0.2, 0.7
    scene, cam, k = simple_scene([[0.0, 0.0, z]], [[s, s, s]], opacities=[o])
    pixels = torch.tensor([[176.0, 64.0], [180.0, 61.0], [190.0, 64.0]], dtype=torch.float64)
    result = render(scene, cam, k, pixels)
    var = (250.0 * s / z) ** 2 + 0.3
    r2 = (pixels - torch.tensor([176.0, 64.0], dtype=torch.float64)).square().sum(-1)
    alpha = o * torch.exp(-0.5 * r2 / var)
    torch.testing.assert_close(result.alpha, alpha)
    torch.testing.assert_close(result.depth, alpha * z)
    torch.testing.assert_close(result.features, alpha[:, None] * scene["features"])


def test_field_of_view_clamp_matches_reference():
    # Large Gaussians centred outside the image at steep angles: the Jacobian clamp matters.
    scene, cam, k = simple_scene([[12.0, 0.0, 2.0], [-9.0, 3.0, 1.5], [0.5, 6.0, 1.0]],
                                 [[3.0, 1.0, 0.5], [2.0, 2.0, 2.0], [1.0, 4.0, 1.0]],
                                 opacities=[0.9, 0.9, 0.9])
    pixels = grid_pixels(4)
    result = render(scene, cam, k, pixels)
    assert (result.alpha > 0).any()
    assert_matches_reference(result, reference(scene, cam, k, pixels))


@pytest.mark.parametrize("dense", [False, True])
def test_tiles_and_depth_batches_do_not_change_result(monkeypatch, dense):
    scene, cam, k, pixels = random_scene(11, 300, 400, dense=dense)
    base = render(scene, cam, k, pixels)
    configs = ((997, 2), (3001, 5), (10**9, 500))      # (candidates per batch, tile size)
    for chunk, tile_size in configs if dense else ((211, 3),) + configs:
        monkeypatch.setattr(splat_module, "CANDIDATE_CHUNK", chunk)
        monkeypatch.setattr(splat_module, "LATER_CANDIDATE_CHUNK", chunk)
        other = render(scene, cam, k, pixels, tile_size=tile_size)
        for a, b in zip(base, other):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)
    # Gradients too: the running transmittance is carried across depth batches.
    monkeypatch.setattr(splat_module, "CANDIDATE_CHUNK", 997)
    monkeypatch.setattr(splat_module, "LATER_CANDIDATE_CHUNK", 997)
    batched = backward_grads(scene, cam, k, pixels)
    monkeypatch.setattr(splat_module, "CANDIDATE_CHUNK", 10**9)
    single = backward_grads(scene, cam, k, pixels)
    for name in single:
        torch.testing.assert_close(batched[name], single[name], atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("dense", [False, True])
def test_wait_free_chunks_equal_compacted_ones(monkeypatch, dense):
    """The rest after the first depth batch, masked (as on a GPU) against compacted with a
    read per chunk (as on the CPU): the same values and gradients, in one chunk and many."""
    scene, cam, k, pixels = random_scene(13, 300, 400, dense=dense)
    names = ("means", "scales", "rotations", "opacities", "features")
    monkeypatch.setattr(splat_module, "CANDIDATE_CHUNK", 997)
    for later in (None, 997):
        monkeypatch.setattr(splat_module, "LATER_CANDIDATE_CHUNK", later)
        out = {}
        for wait_free in (False, True):
            inputs = [scene[n].clone().requires_grad_(True) for n in names]
            result = render_cameras(*inputs, cam[None], k[None], [pixels], HW,
                                    wait_free=wait_free)[0]
            grads = torch.autograd.grad(result.depth.sum() + result.features.square().sum()
                                        + result.alpha.sum(), inputs)
            out[wait_free] = (result, grads)
        assert out[True][0].alpha.max() > 0.5
        for a, b in zip(out[True][0] + out[True][1], out[False][0] + out[False][1]):
            torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)


def test_render_cameras_equals_single_renders():
    scene, cam_a, k, pix_a = random_scene(5, 150, 100)
    _, cam_b, _, pix_b = random_scene(6, 1, 80)
    k_b = k.clone()
    k_b[0, 0] = 180.0
    results = render_cameras(scene["means"], scene["scales"], scene["rotations"],
                             scene["opacities"], scene["features"], torch.stack([cam_a, cam_b]),
                             torch.stack([k, k_b]), [pix_a, pix_b], HW)
    assert len(results) == 2 and isinstance(results[0], RenderResult)
    for result, cam, kk, pix in zip(results, (cam_a, cam_b), (k, k_b), (pix_a, pix_b)):
        single = render(scene, cam, kk, pix)
        for a, b in zip(result, single):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("chunk", [10**9, 997])
def test_render_scenes_equals_each_scene_alone(monkeypatch, chunk):
    """Three scenes of different sizes, each with its own two cameras and pixels, in one call:
    values and gradients as three render_cameras calls (in one depth batch and in many)."""
    monkeypatch.setattr(splat_module, "CANDIDATE_CHUNK", chunk)
    monkeypatch.setattr(splat_module, "LATER_CANDIDATE_CHUNK", chunk)
    names = ("means", "scales", "rotations", "opacities", "features")
    scenes, cams, pixels = [], [], []
    for seed, (num_gaussians, num_pixels) in enumerate([(120, 90), (40, 60), (200, 30)]):
        scene, cam_a, k, pix_a = random_scene(10 + seed, num_gaussians, num_pixels, dense=True)
        _, cam_b, _, pix_b = random_scene(20 + seed, 1, num_pixels // 2)
        scenes.append({n: scene[n].clone().requires_grad_(True) for n in names})
        cams.append(torch.stack([cam_a, cam_b]))
        pixels.append([pix_a, pix_b])
    ks = k.expand(3, 2, 3, 3)
    joint = render_scenes([[s[n] for n in names] for s in scenes], torch.stack(cams), ks,
                          pixels, HW)
    joint_grads = torch.autograd.grad(
        sum(r.depth.sum() + r.features.square().sum() + r.alpha.sum()
            for per_scene in joint for r in per_scene),
        [s[n] for s in scenes for n in names])
    for i, scene in enumerate(scenes):
        alone = render_cameras(*(scene[n] for n in names), cams[i], ks[i], pixels[i], HW)
        grads = torch.autograd.grad(sum(r.depth.sum() + r.features.square().sum()
                                        + r.alpha.sum() for r in alone),
                                    [scene[n] for n in names])
        assert len(joint[i]) == 2
        for ours, single in zip(joint[i], alone):
            assert single.alpha.max() > 0.5          # the scene is seen by its camera
            for a, b in zip(ours, single):     # float64 sums of more pairs: last-bit rounding
                torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)
        for a, b in zip(joint_grads[5 * i:5 * i + 5], grads):
            torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-9)


def test_host_reads_per_call_two_whatever_the_depth_batches(monkeypatch):
    """What makes the host wait for the device (counted as on CUDA): one read of every size
    and check before compositing and one read of the first depth batch's kept pairs' count
    with the rest's size; the projection, the rest's chunks and the backward pass none. So a
    call waits twice, however many chunks the rest takes, none included."""
    from odg_ros.bench.census import Census, CensusMode
    batches = []
    candidate_pairs = splat_module._candidate_pairs
    monkeypatch.setattr(splat_module, "_candidate_pairs",
                        lambda *args: batches.append(1) or candidate_pairs(*args))
    names = ("means", "scales", "rotations", "opacities", "features")
    scenes, pixels = [], []
    for seed in range(3):
        scene, cam, k, pix = random_scene(30 + seed, 60, 40, dense=True)
        scenes.append([scene[n].clone().requires_grad_(True) for n in names])
        pixels.append([pix])
    for first, later in ((10**9, None), (300, None), (300, 300)):
        monkeypatch.setattr(splat_module, "CANDIDATE_CHUNK", first)
        monkeypatch.setattr(splat_module, "LATER_CANDIDATE_CHUNK", later)
        batches.clear()
        census = Census()
        with CensusMode(census, None):
            results = render_scenes(scenes, cam.expand(3, 1, 4, 4), k.expand(3, 1, 3, 3),
                                    pixels, HW, wait_free=True)
            sum(r[0].depth.sum() + r[0].alpha.sum() for r in results).backward()
        syncs = sum(census.syncs.values())
        assert syncs == 2, census.report()
        assert len(batches) == {10**9: 1, 300: 2}[first] if later is None else \
            len(batches) > 3, (first, later, len(batches))


def test_tile_indices_are_valid_for_any_pixel_value():
    """Pixels are binned before the input checks are read: a NaN or inf pixel must still
    give a tile index in range (on CUDA an index out of range is a device-side abort, not
    the clear error the checks raise)."""
    grid = _TileGrid(40, 70, 16, 2)
    values = torch.tensor([float("nan"), float("inf"), -float("inf"), -1e30, 1e30, -3.0, 69.9])
    for index, size in ((grid.column(values), grid.tiles_x), (grid.row(values), grid.tiles_y)):
        assert ((index >= 0) & (index < size)).all(), index


def test_render_scenes_rejects_mismatched_scenes():
    scene, cam, k, pix = random_scene(1, 10, 5)
    gaussians = [scene[n] for n in ("means", "scales", "rotations", "opacities", "features")]
    with pytest.raises(ValueError, match="2 scenes need cam_from_ego"):
        render_scenes([gaussians, gaussians], cam[None, None], k[None, None], [[pix]] * 2, HW)
    with pytest.raises(ValueError, match="scene 1 is torch.float32"):
        render_scenes([gaussians, [t.float() for t in gaussians]], cam.expand(2, 1, 4, 4),
                      k.expand(2, 1, 3, 3), [[pix]] * 2, HW)
    with pytest.raises(ValueError, match="scales must be"):
        render_scenes([gaussians[:1] + [gaussians[1][:3]] + gaussians[2:]],
                      cam[None, None], k[None, None], [[pix]], HW)
    assert render_scenes([], cam[None, None][:0], k[None, None][:0], [], HW) == []


# ----------------------------------------------------------------------------- gradients
def test_gradcheck_tiny_scene():
    # 3 overlapping Gaussians at 4 pixels, away from every cut-off (alpha in ~[0.1, 0.8],
    # T far above 1e-4, centres inside the fov clamp, distinct depths).
    scene, cam, k = simple_scene([[0.1, 0.0, 4.0], [0.2, 0.1, 5.0], [-0.1, 0.05, 6.0]],
                                 [[0.5, 0.3, 0.4], [0.4, 0.6, 0.3], [0.6, 0.5, 0.5]],
                                 opacities=[0.5, 0.6, 0.7],
                                 rotations=[[0.9, 0.1, -0.2, 0.3], [1.0, 0.3, 0.2, -0.1],
                                            [0.7, -0.2, 0.4, 0.1]])
    pixels = torch.tensor([[180.0, 60.0], [185.5, 70.5], [170.0, 66.0], [190.0, 58.0]],
                          dtype=torch.float64)
    names = ("means", "scales", "rotations", "opacities", "features")
    inputs = tuple(scene[n].clone().requires_grad_(True) for n in names)

    def fn(*args):
        r = render_gaussians(*args, cam, k, pixels, HW)
        return r.depth, r.features, r.alpha

    out = fn(*inputs)
    per_pixel_contributions = out[2]
    assert (per_pixel_contributions > 0.3).all()
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradcheck_across_depth_batches_with_early_stop(monkeypatch):
    # One splat per depth batch; every pixel stops after 4 of the 7 Gaussians (T = 2.2e-4 ..
    # 3.3e-4 after the 4th, 2.8e-5 .. 5.8e-5 after the 5th), far enough from 1e-4 that finite
    # differences do not cross the cut-off.
    monkeypatch.setattr(splat_module, "CANDIDATE_CHUNK", 1)
    monkeypatch.setattr(splat_module, "LATER_CANDIDATE_CHUNK", 1)
    z = [3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]
    scene, cam, k = simple_scene([[0.02 * i, -0.01 * i, d] for i, d in enumerate(z)],
                                 [[0.4, 0.35, 0.3]] * 7, opacities=[0.88] * 7)
    pixels = torch.tensor([[176.5, 64.5], [177.0, 63.0], [175.0, 65.5]], dtype=torch.float64)
    names = ("means", "scales", "rotations", "opacities", "features")
    inputs = tuple(scene[n].clone().requires_grad_(True) for n in names)

    def fn(*args):
        r = render_gaussians(*args, cam, k, pixels, HW)
        return r.depth, r.features, r.alpha

    alpha = fn(*inputs)[2]
    assert (alpha > 1 - 1e-3).all()     # the early stop is active at every pixel
    # fast mode (random directional derivatives): the full check is test_gradcheck_tiny_scene.
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_pair_weighted_sum_value_and_gradcheck():
    weight = torch.rand(9, dtype=torch.float64, requires_grad=True)
    values = torch.rand(4, 3, dtype=torch.float64, requires_grad=True)
    # Unsorted pixels, as the depth batches produce them; pixel 3 has no pair.
    pixel = torch.tensor([2, 0, 4, 1, 2, 0, 4, 2, 4])
    splat = torch.tensor([0, 0, 1, 3, 2, 1, 2, 3, 3])
    out = _PairWeightedSum.apply(weight, values, pixel, splat, 5)
    expected = torch.zeros(5, 3, dtype=torch.float64).index_add(
        0, pixel, weight[:, None] * values[splat])
    torch.testing.assert_close(out, expected)
    assert torch.autograd.gradcheck(
        lambda w, v: _PairWeightedSum.apply(w, v, pixel, splat, 5), (weight, values))
    empty = torch.zeros(0, dtype=torch.long)
    assert torch.autograd.gradcheck(
        lambda w, v: _PairWeightedSum.apply(w, v, empty, empty, 5),
        (weight[:0].detach().requires_grad_(True), values))


def test_gradients_finite_and_nonzero_on_random_scene(monkeypatch):
    monkeypatch.setattr(splat_module, "CHECK_CSR", True)   # sorted, unique, in range
    scene, cam, k, pixels = random_scene(8, 400, 300, dtype=torch.float32)
    for t in scene.values():
        t.requires_grad_(True)
    grads = backward_grads(scene, cam, k, pixels)
    for name, grad in grads.items():
        assert grad is not None and torch.isfinite(grad).all(), name
        assert grad.abs().sum() > 0, name


# ----------------------------------------------------------------------------- hard cases
def test_behind_camera_and_on_near_plane_are_culled():
    scene, cam, k = simple_scene([[0.0, 0.0, -5.0], [0.0, 0.0, NEAR], [0.0, 0.0, 0.0]],
                                 [[1.0, 1.0, 1.0]] * 3, opacities=[1.0, 1.0, 1.0])
    pixels = grid_pixels(16)
    result = render(scene, cam, k, pixels)
    assert torch.equal(result.alpha, torch.zeros_like(result.alpha))
    assert torch.equal(result.depth, torch.zeros_like(result.depth))
    grads = backward_grads(scene, cam, k, pixels)
    assert all(torch.isfinite(g).all() for g in grads.values() if g is not None)

    # Just past the near plane: a huge splat, still finite and matching the reference.
    scene, cam, k = simple_scene([[0.0, 0.0, NEAR * 1.001]], [[0.3, 0.3, 0.3]])
    result = render(scene, cam, k, pixels)
    assert (result.alpha > 0.5).all()
    assert_matches_reference(result, reference(scene, cam, k, pixels))
    grads = backward_grads(scene, cam, k, pixels)
    assert all(torch.isfinite(g).all() for g in grads.values())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_extreme_and_degenerate_scales(dtype):
    scene, cam, k = simple_scene(
        [[0.0, 0.0, 10.0], [1.0, 0.0, 8.0], [-1.0, 0.5, 9.0], [0.5, -0.5, 7.0], [0.0, 0.0, 0.5]],
        [[1e3, 1e3, 1e3], [1e-6, 1e-6, 1e-6], [0.5, 0.0, 0.5], [1e-7, 0.8, 1e-7],
         [1e3, 1e-6, 0.0]],
        rotations=[[1, 0, 0, 0], [0.9, 0.1, 0.2, 0.3], [0.5, 0.5, 0.5, 0.5], [1, 2, 3, 4],
                   [0.3, -0.2, 0.9, 0.1]],
        opacities=[0.3, 0.9, 0.9, 0.9, 0.5])
    scene = {n: t.to(dtype) for n, t in scene.items()}
    pixels = torch.cat([grid_pixels(8), torch.tensor([[176.0, 64.0], [176.5, 64.5]],
                                                     dtype=torch.float64)]).to(dtype)
    result = render(scene, cam.to(dtype), k.to(dtype), pixels)
    for value in result:
        assert torch.isfinite(value).all()
    # 1e3 m splats have ~1e11 px^2 covariances: the textbook a c - b^2 loses ~1e-5 relative
    # in float64 (ours uses |A_u x A_v|^2 and does not), so the reference runs in long double.
    expected = reference(scene, cam.double(), k.double(), pixels.double(), dtype=np.longdouble)
    tol = 1e-8 if dtype == torch.float64 else 1e-3
    assert_matches_reference(result, expected, atol=tol, rtol=tol)
    grads = backward_grads(scene, cam.to(dtype), k.to(dtype), pixels)
    for name, grad in grads.items():
        assert torch.isfinite(grad).all(), name


def test_projection_overflow_raises_one_clear_error():
    # float32: a 1e30 m covariance overflows to inf in the image plane
    scene, cam, k = simple_scene([[0.0, 0.0, 10.0], [0.5, 0.0, 8.0]],
                                 [[1e30, 1e30, 1e30], [0.5, 0.5, 0.5]])
    scene = {n: t.float() for n, t in scene.items()}
    with pytest.raises(FloatingPointError, match="projection overflowed"):
        render(scene, cam.float(), k.float(), grid_pixels(4).float())


def test_zero_and_full_opacity():
    scene, cam, k = simple_scene([[0.0, 0.0, 5.0], [0.0, 0.0, 10.0]], [[0.2, 0.2, 0.2]] * 2,
                                 opacities=[0.0, 1.0])
    pixels = torch.tensor([[176.0, 64.0]], dtype=torch.float64)   # exactly at both centres
    result = render(scene, cam, k, pixels)
    # Zero opacity contributes nothing; opacity 1 is capped at alpha 0.99.
    torch.testing.assert_close(result.alpha, torch.tensor([0.99], dtype=torch.float64))
    torch.testing.assert_close(result.depth, torch.tensor([9.9], dtype=torch.float64))
    grads = backward_grads(scene, cam, k, pixels)
    assert all(torch.isfinite(g).all() for g in grads.values())


def test_zero_and_denormal_quaternions_act_as_identity():
    means = [[0.0, 0.0, 6.0], [0.5, 0.2, 7.0], [-0.4, 0.1, 8.0]]
    scales = [[0.5, 0.1, 0.3]] * 3
    identity, cam, k = simple_scene(means, scales, features=[[1.0], [2.0], [3.0]],
                                    rotations=[[1.0, 0, 0, 0]] * 3)
    odd = dict(identity)
    odd["rotations"] = torch.tensor([[0.0, 0, 0, 0], [5e-324, 0, 0, 0], [0, 1e-310, 0, 0]],
                                    dtype=torch.float64)
    pixels = grid_pixels(8)
    a, b = render(identity, cam, k, pixels), render(odd, cam, k, pixels)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y)
    grads = backward_grads(odd, cam, k, pixels)
    assert all(torch.isfinite(g).all() for g in grads.values())
    for dtype in (torch.float32,):
        tiny = {n: t.detach().to(dtype) for n, t in odd.items()}
        tiny["rotations"] = torch.tensor([[1e-40, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1e-39, 0]],
                                         dtype=dtype)
        grads = backward_grads(tiny, cam.to(dtype), k.to(dtype), pixels.to(dtype))
        assert all(torch.isfinite(g).all() for g in grads.values())


def test_coincident_means_composite_in_index_order():
    scene, cam, k = simple_scene([[0.2, 0.1, 5.0]] * 3, [[0.3, 0.3, 0.3]] * 3,
                                 opacities=[0.5, 0.5, 0.5], features=[[1.0], [2.0], [3.0]])
    pixels = grid_pixels(4)
    result = render(scene, cam, k, pixels)
    assert_matches_reference(result, reference(scene, cam, k, pixels))
    centre = render(scene, cam, k, torch.tensor([[186.0, 69.0]], dtype=torch.float64))
    # 0.5 * 1 + 0.25 * 2 + 0.125 * 3 at the common centre.
    torch.testing.assert_close(centre.features, torch.tensor([[1.375]], dtype=torch.float64))
    grads = backward_grads(scene, cam, k, pixels)
    assert all(torch.isfinite(g).all() for g in grads.values())


def test_early_stop_is_exclusive():
    # alpha = o exactly at the common centre; (1 - o)^4 = 0.9e-4 <= 1e-4, so the 4th Gaussian
    # is excluded and compositing stops with T = (1 - o)^3.
    o = 1.0 - 0.9e-4 ** 0.25
    z = [4.0, 5.0, 6.0, 7.0, 8.0]
    scene, cam, k = simple_scene([[0.0, 0.0, d] for d in z], [[0.3, 0.3, 0.3]] * 5,
                                 opacities=[o] * 5)
    result = render(scene, cam, k, torch.tensor([[176.0, 64.0]], dtype=torch.float64))
    weights = [o * (1 - o) ** i for i in range(3)]
    torch.testing.assert_close(result.alpha, torch.tensor([1 - (1 - o) ** 3],
                                                          dtype=torch.float64))
    torch.testing.assert_close(result.depth, torch.tensor([sum(w * d for w, d in zip(weights, z))],
                                                          dtype=torch.float64))


def test_thousands_of_gaussians_in_one_pixel_stop_early():
    n = 3000
    z = torch.linspace(2.0, 60.0, n, dtype=torch.float64)
    means = torch.stack([torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64),
                         z], dim=-1)
    scene, cam, k = simple_scene(means.tolist(), [[0.5, 0.5, 0.5]] * n,
                                 opacities=[0.6] * n)
    pixels = torch.tensor([[176.5, 64.5], [176.0, 64.0], [300.0, 100.0]], dtype=torch.float64)
    result = render(scene, cam, k, pixels)
    assert_matches_reference(result, reference(scene, cam, k, pixels))
    # Stopped exclusively before T reached 1e-4.
    assert (result.alpha[:2] > 1 - 1e-3).all() and (result.alpha[:2] < 1 - 1e-4).all()
    grads = backward_grads(scene, cam, k, pixels)
    assert all(torch.isfinite(g).all() for g in grads.values())
    # Gaussians far behind the stopping point get no gradient.
    assert grads["features"][n // 2:].abs().sum() == 0
    assert grads["features"][0].abs().sum() > 0


def test_no_gaussian_in_view_gives_zeros_and_a_graph():
    scene, cam, k = simple_scene([[0.0, 0.0, -3.0], [100.0, 0.0, 1.0]], [[0.5, 0.5, 0.5]] * 2)
    pixels = grid_pixels(16)
    result = render(scene, cam, k, pixels)
    assert torch.equal(result.depth, torch.zeros(len(pixels), dtype=torch.float64))
    assert torch.equal(result.alpha, torch.zeros(len(pixels), dtype=torch.float64))
    assert torch.equal(result.features, torch.zeros(len(pixels), 3, dtype=torch.float64))
    grads = backward_grads(scene, cam, k, pixels)
    assert grads["features"] is not None and grads["features"].abs().sum() == 0


def test_empty_inputs():
    scene, cam, k = simple_scene([[0.0, 0.0, 5.0]], [[0.5, 0.5, 0.5]])
    none = {n: t[:0] for n, t in scene.items()}
    result = render(none, cam, k, grid_pixels(32))
    assert result.features.shape == (len(grid_pixels(32)), 3)
    assert not result.alpha.any() and not result.depth.any()
    result = render(scene, cam, k, torch.zeros(0, 2, dtype=torch.float64))
    assert result.depth.shape == (0,) and result.features.shape == (0, 3)
    assert result.alpha.shape == (0,)
    results = render_cameras(scene["means"], scene["scales"], scene["rotations"],
                             scene["opacities"], scene["features"], cam[None][:0], k[None][:0], [], HW)
    assert results == []


def test_bad_input_raises_clear_errors():
    scene, cam, k = simple_scene([[0.0, 0.0, 5.0]], [[0.5, 0.5, 0.5]])
    pixels = torch.tensor([[10.0, 10.0]], dtype=torch.float64)
    bad = dict(scene, means=torch.tensor([[0.0, float("nan"), 5.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="means contains NaN"):
        render(bad, cam, k, pixels)
    with pytest.raises(ValueError, match="inside"):
        render(scene, cam, k, torch.tensor([[400.0, 10.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="scales must be"):
        render(dict(scene, scales=scene["scales"][:, :2]), cam, k, pixels)
    with pytest.raises(ValueError, match="rigid"):
        render(scene, cam * 2, k, pixels)
    with pytest.raises(ValueError, match="float64"):
        render(dict(scene, opacities=scene["opacities"].float()), cam, k, pixels)


def test_autocast_and_half_precision_inputs_render_in_float32():
    scene, cam, k, pixels = random_scene(12, 200, 200, dtype=torch.float32)
    plain = render(scene, cam, k, pixels)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        autocast = render(scene, cam, k, pixels)
    for a, b in zip(plain, autocast):
        assert b.dtype == torch.float32
        torch.testing.assert_close(a, b)
    half = {n: t.bfloat16() for n, t in scene.items()}
    result = render(half, cam, k, pixels)
    rounded = render({n: t.float() for n, t in half.items()}, cam, k, pixels)
    for a, b in zip(rounded, result):
        assert b.dtype == torch.float32
        torch.testing.assert_close(a, b)
