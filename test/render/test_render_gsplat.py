"""Our renderer against gsplat's own code, on CPU; and our gsplat backend (the last tests).

gsplat's rasteriser is CUDA-only, but the package ships pure-PyTorch versions of its
projection (`gsplat.cuda._torch_impl`, what gsplat's own tests check its kernels against).
Projecting with that code and compositing with the rules of gsplat's forward kernel
(RasterizeToPixels3DGSFwd.cu: front to back by depth, skip power < 0 or alpha < 1/255, stop
before the Gaussian that takes T to <= 1e-4) must give what `render_cameras` gives, at every
pixel of every camera. One deliberate difference: gsplat caps alpha at 0.999, the Inria
rasteriser at 0.99 (ours). The scenes below keep opacities under 0.95, where
neither cap can act, except the saturated test, which composites with our cap.
"""
import numpy as np
import pytest
import torch
from gsplat.cuda import _torch_impl as gsplat_reference

from odg_ros.render import render_cameras
from odg_ros.render.projection import ALPHA_MAX, ALPHA_MIN, BLUR_PX2, project_gaussians
from testing.render import look_transform

NEAR = 0.05
HW = (36, 64)
GSPLAT_ALPHA_MAX = 0.999
GSPLAT_TRANSMITTANCE_STOP = 1e-4   # the forward kernel's literal (ours: splat.TRANSMITTANCE_MIN)


def rig(rng, num_cameras):
    """cam_from_ego [N, 4, 4] (random yaw, pitch, position) and intrinsics [N, 3, 3] with
    different focal lengths and off-centre principal points."""
    cam_from_ego, intrinsics = [], []
    for _ in range(num_cameras):
        yaw, pitch = rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3)
        cam_from_ego.append(look_transform(yaw, pitch, rng.uniform(-1.5, 1.5, 3)))
        focal = rng.uniform(30.0, 70.0)
        intrinsics.append([[focal * rng.uniform(0.9, 1.1), 0.0, HW[1] * rng.uniform(0.4, 0.6)],
                           [0.0, focal, HW[0] * rng.uniform(0.4, 0.6)], [0.0, 0.0, 1.0]])
    return (torch.tensor(np.stack(cam_from_ego), dtype=torch.float64),
            torch.tensor(intrinsics, dtype=torch.float64))


def random_gaussians(rng, num, max_opacity=0.95):
    """Gaussians all around the rig: behind, beside (far outside the field of view, where the
    Jacobian clamp acts), on the near plane; scales from 1 cm to 3 m, some flat or needles."""
    scales = np.exp(rng.uniform(np.log(0.01), np.log(3.0), (num, 3)))
    flat = rng.random(num) < 0.2
    scales[flat, rng.integers(0, 3, flat.sum())] = 1e-6
    gaussians = dict(
        means=rng.uniform(-12.0, 12.0, (num, 3)) * [1.0, 1.0, 0.3],
        scales=scales,
        rotations=rng.normal(size=(num, 4)),
        opacities=rng.uniform(0.0, max_opacity, num),
        features=rng.uniform(0.0, 1.0, (num, 4)),
    )
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in gaussians.items()}


def gsplat_projection(g, cam_from_ego, intrinsics):
    """gsplat's reference projection: radii [N, G, 2], means2d [N, G, 2], depths [N, G],
    conics [N, G, 3] (inverse 2D covariance: a, b, c of a u^2 + 2 b u v + c v^2)."""
    covars, _ = gsplat_reference._quat_scale_to_covar_preci(
        g["rotations"], g["scales"], compute_covar=True, compute_preci=False)
    radii, means2d, depths, conics, _ = gsplat_reference._fully_fused_projection(
        g["means"], covars, cam_from_ego, intrinsics, HW[1], HW[0], eps2d=BLUR_PX2,
        near_plane=NEAR)
    return radii, means2d, depths, conics


def pixel_centres():
    """u, v [H * W] of every pixel centre, row-major."""
    v, u = torch.meshgrid(torch.arange(HW[0], dtype=torch.float64) + 0.5,
                          torch.arange(HW[1], dtype=torch.float64) + 0.5, indexing="ij")
    return u.flatten(), v.flatten()


def conic_power(conic, mean2d, u, v):
    """gsplat's exponent 0.5 d^T conic d at pixels (u, v) for one splat."""
    a, b, c = conic
    du, dv = mean2d[0] - u, mean2d[1] - v
    return 0.5 * (a * du * du + c * dv * dv) + b * du * dv


def gsplat_composite(g, cam_from_ego, intrinsics, alpha_max=GSPLAT_ALPHA_MAX):
    """Every pixel of every camera composited as gsplat's forward kernel does (float64).
    Returns [N, H * W, C + 2]: features, depth, accumulated alpha (row-major pixels); the
    pixels (u, v) [H * W, 2]; and which pixels reached the early stop [N, H * W]."""
    radii, means2d, depths, conics = gsplat_projection(g, cam_from_ego, intrinsics)
    pixel_u, pixel_v = pixel_centres()
    out, stopped = [], []
    for cam in range(cam_from_ego.shape[0]):
        listed = (radii[cam] > 0).all(-1).nonzero().flatten()
        order = listed[torch.argsort(depths[cam, listed], stable=True)]
        transmittance = torch.ones_like(pixel_u)
        done = torch.zeros_like(pixel_u, dtype=torch.bool)
        values = torch.zeros(pixel_u.shape[0], g["features"].shape[1] + 2, dtype=torch.float64)
        for i in order.tolist():
            power = conic_power(conics[cam, i], means2d[cam, i], pixel_u, pixel_v)
            alpha = torch.clamp_max(g["opacities"][i] * torch.exp(-power), alpha_max)
            hit = ~done & (power >= 0) & (alpha >= ALPHA_MIN)
            next_t = transmittance * (1.0 - alpha)
            done = done | (hit & (next_t <= GSPLAT_TRANSMITTANCE_STOP))
            hit = hit & ~done
            weight = torch.where(hit, alpha * transmittance, torch.zeros_like(alpha))
            value = torch.cat([g["features"][i], depths[cam, i, None],
                               torch.ones(1, dtype=torch.float64)])
            values += weight[:, None] * value
            transmittance = torch.where(hit, next_t, transmittance)
        out.append(values)
        stopped.append(done)
    return torch.stack(out), torch.stack([pixel_u, pixel_v], dim=-1), torch.stack(stopped)


def render_all_pixels(g, cam_from_ego, intrinsics, pixels):
    results = render_cameras(g["means"], g["scales"], g["rotations"], g["opacities"],
                             g["features"], cam_from_ego, intrinsics,
                             [pixels] * cam_from_ego.shape[0], HW, near=NEAR)
    return torch.stack([torch.cat([r.features, r.depth[:, None], r.alpha[:, None]], dim=-1)
                        for r in results])


def assert_same_gradients(actual, desired, inputs, weights):
    """d(sum(weights * output)) w.r.t. each of ``inputs`` (name -> tensor): actual's equal
    desired's (rtol 1e-6, float64), and neither is all zero."""
    actual_grads = torch.autograd.grad((actual * weights).sum(), list(inputs.values()))
    desired_grads = torch.autograd.grad((desired * weights).sum(), list(inputs.values()))
    for name, a, d in zip(inputs, actual_grads, desired_grads):
        assert a.abs().max() > 0 and d.abs().max() > 0, name
        np.testing.assert_allclose(a.numpy(), d.numpy(), rtol=1e-6,
                                   atol=1e-9 * d.abs().max().item(), err_msg=name)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projection_matches_gsplat(seed):
    """Projected centre, inverse 2D covariance and depth of every splat we keep equal
    gsplat's, and every splat gsplat projects that reaches alpha >= 1/255 at some pixel
    centre is one we keep (our cull never drops a contribution)."""
    rng = np.random.default_rng(seed)
    cam_from_ego, intrinsics = rig(rng, 3)
    g = random_gaussians(rng, 600)
    radii, means2d, depths, conics = gsplat_projection(g, cam_from_ego, intrinsics)
    ours = project_gaussians(g["means"], g["scales"], g["rotations"], g["opacities"],
                             cam_from_ego, intrinsics, HW, NEAR)
    assert len(ours) > 100
    cam, gauss = ours.camera, ours.gaussian
    np.testing.assert_allclose(ours.mean2d.numpy(), means2d[cam, gauss].numpy(),
                               rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(ours.depth.numpy(), depths[cam, gauss].numpy(), rtol=1e-12)
    our_conics = torch.stack([ours.cov_yy / ours.det, -ours.cov_xy / ours.det,
                              ours.cov_xx / ours.det], dim=-1)
    np.testing.assert_allclose(our_conics.numpy(), conics[cam, gauss].numpy(),
                               rtol=1e-7, atol=1e-12)
    assert (radii[cam, gauss] > 0).all(), "we keep a splat gsplat culls"

    u, v = pixel_centres()
    kept = set(zip(cam.tolist(), gauss.tolist()))
    checked = 0
    for c, i in (radii > 0).all(-1).nonzero().tolist():
        if (c, i) in kept:
            continue
        power = conic_power(conics[c, i], means2d[c, i], u, v)
        alpha = g["opacities"][i] * torch.exp(-power)
        assert not ((power >= 0) & (alpha >= ALPHA_MIN)).any(), (c, i)
        checked += 1
    assert checked > 0   # the scenes do have splats that gsplat lists and we can drop


@pytest.mark.parametrize("seed", [3, 4])
def test_render_matches_gsplat_projection_and_kernel_rules(seed):
    rng = np.random.default_rng(seed)
    cam_from_ego, intrinsics = rig(rng, 2)
    g = random_gaussians(rng, 1500)
    expected, pixels, stopped = gsplat_composite(g, cam_from_ego, intrinsics)
    rendered = render_all_pixels(g, cam_from_ego, intrinsics, pixels)
    assert (expected[..., -1] > 0.1).float().mean() > 0.3 and stopped.any()   # a real picture
    np.testing.assert_allclose(rendered.numpy(), expected.numpy(), rtol=1e-7, atol=1e-9)


def test_saturated_opacities_match_with_our_alpha_cap():
    """Opacities up to 1: with our 0.99 cap in gsplat's kernel rules the results agree; with
    gsplat's 0.999 they do not (the one convention we take from Inria instead)."""
    rng = np.random.default_rng(5)
    cam_from_ego, intrinsics = rig(rng, 2)
    g = random_gaussians(rng, 400, max_opacity=1.0)
    g["opacities"][::3] = 1.0
    expected, pixels, stopped = gsplat_composite(g, cam_from_ego, intrinsics,
                                                 alpha_max=ALPHA_MAX)
    assert stopped.any()
    rendered = render_all_pixels(g, cam_from_ego, intrinsics, pixels)
    np.testing.assert_allclose(rendered.numpy(), expected.numpy(), rtol=1e-7, atol=1e-9)
    gsplat_capped, _, _ = gsplat_composite(g, cam_from_ego, intrinsics)
    assert (gsplat_capped - expected).abs().max() > 1e-3


def test_projection_gradients_match_gsplat():
    """The same function, so the same gradients: d(centre, inverse covariance, depth) w.r.t.
    means, scales and quaternions through our projection (Lagrange-identity determinant,
    clamped Jacobian) equal autograd through gsplat's, float64."""
    rng = np.random.default_rng(6)
    cam_from_ego, intrinsics = rig(rng, 2)
    g = random_gaussians(rng, 300)
    params = {k: g[k].clone().requires_grad_(True) for k in ("means", "scales", "rotations")}
    ours = project_gaussians(params["means"], params["scales"], params["rotations"],
                             g["opacities"], cam_from_ego, intrinsics, HW, NEAR)
    cam, gauss = ours.camera, ours.gaussian
    ours_out = torch.cat([ours.mean2d, ours.depth[:, None], torch.stack(
        [ours.cov_yy / ours.det, -ours.cov_xy / ours.det, ours.cov_xx / ours.det], dim=-1)], -1)
    _, means2d, depths, conics = gsplat_projection({**g, **params}, cam_from_ego, intrinsics)
    theirs_out = torch.cat([means2d[cam, gauss], depths[cam, gauss, None],
                            conics[cam, gauss]], dim=-1)
    # Scale each output column to order 1 so no one term dominates the comparison.
    weights = (torch.tensor(rng.normal(size=ours_out.shape))
               / theirs_out.detach().abs().clamp_min(1e-3))
    assert_same_gradients(ours_out, theirs_out, params, weights)


# --------------------------------------------------------------------------------------------
# odg_ros.render.gsplat_backend: our code calling gsplat.rasterization.
# On CPU, gsplat.rasterization's own Python runs with its four CUDA kernels replaced by
# gsplat's pure-PyTorch versions (projection, tile intersections) and by the forward kernel's
# rules written out (rasterisation, per tile as the kernel does); that checks everything of
# ours (conventions, layouts, reading pixels back, gradients) but the kernels themselves,
# which gsplat's own tests check against the same pure-PyTorch code. On a CUDA machine the
# last test runs the real kernels.

def _projection_without_cuda(means, covars, quats, scales, viewmats, Ks, width, height,
                             eps2d=0.3, packed=True, near_plane=0.01, far_plane=1e10,
                             radius_clip=0.0, sparse_grad=False, calc_compensations=False,
                             camera_model="pinhole", opacities=None):
    assert not packed and covars is None and camera_model == "pinhole" and radius_clip == 0.0
    covars, _ = gsplat_reference._quat_scale_to_covar_preci(quats, scales, True, False,
                                                            triu=False)
    return gsplat_reference._fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane,
        far_plane=far_plane, calc_compensations=calc_compensations)


def _tiles_without_cuda(means2d, radii, depths, tile_size, tile_width, tile_height,
                        segmented=False, packed=False, n_images=None, image_ids=None,
                        gaussian_ids=None):
    assert not packed and not segmented
    return gsplat_reference._isect_tiles(means2d, radii, depths, tile_size, tile_width,
                                         tile_height)


def _rasterize_without_cuda(means2d, conics, colors, opacities, width, height, tile_size,
                            isect_offsets, flatten_ids, backgrounds=None, masks=None,
                            packed=False, absgrad=False):
    """RasterizeToPixels3DGSFwd.cu's rules, tile by tile over the tile's depth-sorted list."""
    assert not packed and backgrounds is None and masks is None
    image_dims, (tiles_y, tiles_x) = isect_offsets.shape[:-2], isect_offsets.shape[-2:]
    images = isect_offsets[..., 0, 0].numel()
    ends = torch.cat([isect_offsets.flatten()[1:].long(),
                      torch.tensor([flatten_ids.numel()])])
    means2d, conics = means2d.reshape(-1, 2), conics.reshape(-1, 3)
    colors, opacities = colors.reshape(-1, colors.shape[-1]), opacities.reshape(-1)
    out = means2d.new_zeros(images, height, width, colors.shape[-1])
    alpha_out = means2d.new_zeros(images, height, width, 1)
    for tile, (start, end) in enumerate(zip(isect_offsets.flatten().long().tolist(),
                                            ends.tolist())):
        image, ty, tx = tile // (tiles_y * tiles_x), tile // tiles_x % tiles_y, tile % tiles_x
        rows = slice(ty * tile_size, min((ty + 1) * tile_size, height))
        cols = slice(tx * tile_size, min((tx + 1) * tile_size, width))
        v, u = torch.meshgrid(torch.arange(rows.start, rows.stop, dtype=means2d.dtype) + 0.5,
                              torch.arange(cols.start, cols.stop, dtype=means2d.dtype) + 0.5,
                              indexing="ij")
        transmittance = torch.ones_like(u)
        done = torch.zeros_like(u, dtype=torch.bool)
        value = u.new_zeros(u.shape + (colors.shape[-1],))
        for i in flatten_ids[start:end].long().tolist():
            power = conic_power(conics[i], means2d[i], u, v)
            alpha = torch.clamp_max(opacities[i] * torch.exp(-power), GSPLAT_ALPHA_MAX)
            hit = ~done & (power >= 0) & (alpha >= ALPHA_MIN)
            next_t = transmittance * (1.0 - alpha)
            done = done | (hit & (next_t <= GSPLAT_TRANSMITTANCE_STOP))
            hit = hit & ~done
            weight = torch.where(hit, alpha * transmittance, torch.zeros_like(alpha))
            value = value + weight[..., None] * colors[i]
            transmittance = torch.where(hit, next_t, transmittance)
        out[image, rows, cols] = value
        alpha_out[image, rows, cols, 0] = 1.0 - transmittance
    return (out.reshape(*image_dims, *out.shape[1:]),
            alpha_out.reshape(*image_dims, *alpha_out.shape[1:]))


@pytest.fixture
def gsplat_kernels_on_cpu(monkeypatch):
    import gsplat.rendering
    monkeypatch.setattr(gsplat.rendering, "fully_fused_projection", _projection_without_cuda)
    monkeypatch.setattr(gsplat.rendering, "isect_tiles", _tiles_without_cuda)
    monkeypatch.setattr(gsplat.rendering, "isect_offset_encode",
                        gsplat_reference._isect_offset_encode)
    monkeypatch.setattr(gsplat.rendering, "rasterize_to_pixels", _rasterize_without_cuda)


def render_with(renderer, g, cam_from_ego, intrinsics, pixels):
    results = renderer(g["means"], g["scales"], g["rotations"], g["opacities"], g["features"],
                       cam_from_ego, intrinsics, pixels, HW, near=NEAR)
    return torch.cat([torch.cat([r.features, r.depth[:, None], r.alpha[:, None]], dim=-1)
                      for r in results])


def test_gsplat_backend_renders_what_ours_does(gsplat_kernels_on_cpu):
    """Same features, depth and alpha at every pixel centre (float64), and a point anywhere in
    a pixel reads that pixel's centre; gradients w.r.t. every Gaussian attribute agree."""
    from odg_ros.render.gsplat_backend import render_cameras_gsplat
    rng = np.random.default_rng(7)
    cam_from_ego, intrinsics = rig(rng, 2)
    g = random_gaussians(rng, 300)
    # Five between gsplat's default near plane (0.01 m) and ours (0.05 m): culled by both.
    in_camera = torch.tensor([[0.01, -0.01, 0.03, 1.0], [0.0, 0.0, 0.02, 1.0],
                              [-0.01, 0.0, 0.04, 1.0], [0.0, 0.01, 0.045, 1.0],
                              [0.005, 0.005, 0.015, 1.0]], dtype=torch.float64)
    g["means"][:5] = (torch.linalg.inv(cam_from_ego[0]) @ in_camera.T).T[:, :3]
    g["scales"][:5] = 0.005
    g["opacities"][:5] = 0.9
    g = {k: v.requires_grad_(True) for k, v in g.items()}
    centres = torch.stack(pixel_centres(), dim=-1)
    ours = render_with(render_cameras, g, cam_from_ego, intrinsics, [centres, centres.flip(0)])
    theirs = render_with(render_cameras_gsplat, g, cam_from_ego, intrinsics,
                         [centres, centres.flip(0)])
    assert (ours[:, -1] > 0.1).float().mean() > 0.3   # a real picture
    np.testing.assert_allclose(theirs.detach().numpy(), ours.detach().numpy(), rtol=1e-7,
                               atol=1e-9)

    assert_same_gradients(theirs, ours, g, torch.tensor(rng.normal(size=ours.shape)))

    inside = centres + torch.tensor(rng.uniform(-0.5, 0.4999, centres.shape))
    inside[-1] = torch.tensor([float(HW[1]), float(HW[0])])   # the far corner: last pixel
    anywhere = render_with(render_cameras_gsplat, g, cam_from_ego, intrinsics,
                           [inside, inside.flip(0)])
    np.testing.assert_array_equal(anywhere.detach().numpy(), theirs.detach().numpy())


def test_render_loss_takes_the_gsplat_backend(gsplat_kernels_on_cpu):
    """The render loss (float32, LiDAR-like targets at pixel centres) is the same with either
    renderer, gradients included: what ``odg train --renderer gsplat`` changes is the kernels."""
    from odg_ros.losses.render_loss import render_loss
    from odg_ros.render.gsplat_backend import render_scenes_gsplat
    rng = np.random.default_rng(9)
    cam_from_ego, intrinsics = rig(rng, 2)
    g = random_gaussians(rng, 200)
    logits = torch.tensor(rng.normal(size=(1, 200, 17)), requires_grad=True)
    centres = torch.stack(pixel_centres(), dim=-1)
    targets = [[torch.cat([centres[rows], torch.tensor(rng.uniform(1.0, 20.0, (300, 1))),
                           torch.tensor(rng.integers(0, 18, (300, 1)))], dim=-1).float()
                for rows in (rng.choice(len(centres), 300, replace=False) for _ in range(2))]]
    losses = []
    for renderer in (None, render_scenes_gsplat):
        result = render_loss(g["means"][None], g["scales"][None], g["rotations"][None],
                             g["opacities"][None], logits, targets, cam_from_ego[None],
                             intrinsics[None], HW, renderer=renderer, near=NEAR)
        grad, = torch.autograd.grad(result.depth + result.semantic, logits)
        losses.append((result.depth.item(), result.semantic.item(), result.num_labelled, grad))
    (depth, semantic, labelled, grad), (g_depth, g_semantic, g_labelled, g_grad) = losses
    assert labelled == g_labelled > 0 and grad.abs().max() > 0
    assert g_depth == pytest.approx(depth, rel=1e-5)
    assert g_semantic == pytest.approx(semantic, rel=1e-5)
    np.testing.assert_allclose(g_grad.numpy(), grad.numpy(), rtol=1e-4, atol=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="gsplat's rasteriser has CUDA kernels only; no GPU on this machine")
def test_gsplat_cuda_kernels_render_what_ours_does():
    """gsplat's real CUDA kernels against our renderer, float32 on the GPU."""
    from odg_ros.render.gsplat_backend import render_cameras_gsplat
    rng = np.random.default_rng(8)
    cam_from_ego, intrinsics = (t.float().cuda() for t in rig(rng, 3))
    g = {k: v.float().cuda().requires_grad_(True)
         for k, v in random_gaussians(rng, 3000).items()}
    centres = torch.stack(pixel_centres(), dim=-1).float().cuda()
    ours = render_with(render_cameras, g, cam_from_ego, intrinsics, [centres] * 3)
    theirs = render_with(render_cameras_gsplat, g, cam_from_ego, intrinsics, [centres] * 3)
    assert (ours[:, -1] > 0.1).float().mean() > 0.3
    # float32 on both sides: a pair right at the 1/255 skip or the 1e-4 stop can fall either
    # way (a step of up to alpha * T at that pixel), so a few pixels may differ by that much.
    error = (theirs - ours).detach().abs() / ours.detach().abs().amax(dim=0)
    assert (error > 1e-4).float().mean() < 1e-3 and error.max() < 0.02, error.max()
    weights = torch.randn(ours.shape, device="cuda")
    ours_grads = torch.autograd.grad((ours * weights).sum(), list(g.values()))
    theirs_grads = torch.autograd.grad((theirs * weights).sum(), list(g.values()))
    for name, a, b in zip(g, ours_grads, theirs_grads):
        assert (b - a).norm() <= 1e-2 * a.norm(), name


def test_scenes_of_different_sizes_in_one_gsplat_call(gsplat_kernels_on_cpu, monkeypatch):
    """render_scenes_gsplat: scenes of 300, 120 and 40 Gaussians (padded to 300 with culled
    ones) in one rasterization call give what our renderer gives for each scene, gradients
    included."""
    import gsplat
    from odg_ros.render import render_scenes
    from odg_ros.render.gsplat_backend import render_scenes_gsplat
    calls = []
    rasterization = gsplat.rasterization
    monkeypatch.setattr(gsplat, "rasterization",
                        lambda *a, **k: calls.append(1) or rasterization(*a, **k))
    rng = np.random.default_rng(11)
    names = ("means", "scales", "rotations", "opacities", "features")
    scenes, cams, ks = [], [], []
    for size in (300, 120, 40):
        cam_from_ego, intrinsics = rig(rng, 2)
        g = random_gaussians(rng, size)
        scenes.append([g[n].requires_grad_(True) for n in names])
        cams.append(cam_from_ego)
        ks.append(intrinsics)
    centres = torch.stack(pixel_centres(), dim=-1)
    pixels = [[centres, centres.flip(0)]] * 3

    def rendered(renderer):
        results = renderer(scenes, torch.stack(cams), torch.stack(ks), pixels, HW, near=NEAR)
        return torch.cat([torch.cat([r.features, r.depth[:, None], r.alpha[:, None]], -1)
                          for per_scene in results for r in per_scene])
    ours, theirs = rendered(render_scenes), rendered(render_scenes_gsplat)
    assert len(calls) == 1 and (ours[:, -1] > 0.1).float().mean() > 0.3
    np.testing.assert_allclose(theirs.detach().numpy(), ours.detach().numpy(), rtol=1e-7,
                               atol=1e-9)
    inputs = [t for scene in scenes for t in scene]
    assert_same_gradients(theirs, ours, dict(enumerate(inputs)),
                          torch.tensor(rng.normal(size=ours.shape)))
