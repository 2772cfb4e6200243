"""Hard cases of the Gaussians and the renderer, beyond test_render.py's fixed cases:
random combinations of zero / denormal / huge quaternions, scales from 1e-6 to 1e3 m per axis
(very flat and needle covariances), opacity 0 and 1, coincident means, thousands of
Gaussians in one pixel, none in view -- checked against the float64 / long-double
brute-force reference of test_render.py, with finite outputs and gradients, and gradcheck in
float64 on small extreme scenes. Also the Phi MLPs (scale, rotation, opacity) on extreme
inputs.

Already covered by test_render.py (fixed cases, not repeated): test_extreme_and_degenerate_scales,
test_zero_and_full_opacity, test_zero_and_denormal_quaternions_act_as_identity,
test_coincident_means_composite_in_index_order, test_thousands_of_gaussians_in_one_pixel_stop_early,
test_no_gaussian_in_view_gives_zeros_and_a_graph.
"""
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from odg_ros.network.gaussian_heads import MAX_SCALE, MIN_SCALE, GaussianAttributes
from odg_ros.render import render_gaussians
from odg_ros.rotation import normalise_quaternions

from testing.hard_cases import FEW, HARD, all_finite, log_uniform
from testing.render import HW, K, reference_render

QUATERNIONS = {"zero": [0.0, 0, 0, 0], "denormal": [5e-324, 0, 0, 0],
               "tiny": [1e-300, 1e-300, 0, 0], "huge": [1e20, -3e19, 2e19, 1e20],
               "identity": [1.0, 0, 0, 0], "half turn": [0.0, 0, 0, 1]}

gaussian = st.fixed_dictionaries({
    "mean": st.tuples(st.floats(-8, 8), st.floats(-3, 3), st.floats(0.06, 30.0)),
    "scale": st.tuples(*[log_uniform(1e-6, 1e3)] * 3),
    "rotation": st.sampled_from(sorted(QUATERNIONS)).map(lambda k: QUATERNIONS[k])
    | st.tuples(*[st.floats(-1, 1)] * 4),
    # >= 0.99 is capped at alpha 0.99; two capped alphas at one pixel put T exactly on the
    # 1e-4 cut (0.01^2): that tie has its own test below, so here only the first may be opaque
    "opacity": st.sampled_from([0.0, 0.98]) | st.floats(0.0, 0.98),
    "feature": st.tuples(*[st.floats(0, 1)] * 3),
})


def scene_tensors(gaussians, coincident, dtype, first_opaque=False):
    if first_opaque:
        gaussians = [dict(gaussians[0], opacity=1.0)] + gaussians[1:]
    means = [g["mean"] for g in gaussians]
    if coincident:
        means = [means[0]] * len(means)
    t = {"means": means, "scales": [g["scale"] for g in gaussians],
         "rotations": [g["rotation"] for g in gaussians],
         "opacities": [g["opacity"] for g in gaussians],
         "features": [g["feature"] for g in gaussians]}
    return {k: torch.tensor(v, dtype=torch.float64).to(dtype) for k, v in t.items()}


def pixels_for(means, dtype):
    """A coarse grid plus each Gaussian's projected centre (clamped into the image)."""
    v, u = torch.meshgrid(torch.arange(4, HW[0], 24.0), torch.arange(4, HW[1], 48.0),
                          indexing="ij")
    grid = torch.stack([u.flatten(), v.flatten()], -1).double()
    m = means.double()
    centres = torch.stack([250.0 * m[:, 0] / m[:, 2] + 176.0, 250.0 * m[:, 1] / m[:, 2] + 64.0],
                          -1)
    centres = torch.stack([centres[:, 0].clamp(0, HW[1]), centres[:, 1].clamp(0, HW[0])], -1)
    return torch.cat([grid, centres]).to(dtype)


def render_scene(scene, pixels):
    cam = torch.eye(4, dtype=scene["means"].dtype)
    k = torch.tensor(K, dtype=scene["means"].dtype)
    return render_gaussians(scene["means"], scene["scales"], scene["rotations"],
                            scene["opacities"], scene["features"], cam, k, pixels, HW)


def reference_of(scene, pixels):
    arrays = [scene[n].detach().double().numpy() for n in
              ("means", "scales", "rotations", "opacities", "features")]
    return reference_render(*arrays, np.eye(4), K, pixels.double().numpy(), HW,
                            dtype=np.longdouble)


def check_invariants(result, scene):
    """Finite; alpha in [0, 1); features are alpha-weighted, so within [0, alpha * max]; the
    depth is an alpha-weighted mean of camera depths."""
    depth, features, alpha = result
    assert all_finite(depth, features, alpha)
    assert (alpha >= 0).all() and (alpha < 1).all()
    # bounds up to the rounding of a sum of products at the values' magnitude (float32 depths
    # of 1e3 m round at ~1e-4 m: an absolute 1e-6 only holds in float64)
    eps = torch.finfo(depth.dtype).eps
    fmax = scene["features"].max() if len(scene["features"]) else 0.0
    ftol = 1e-6 + 16 * eps * float(fmax)
    assert (features >= -1e-12).all() and (features <= alpha[:, None] * fmax + ftol).all()
    zmax = scene["means"][:, 2].max() if len(scene["means"]) else 0.0
    ztol = 1e-6 + 16 * eps * float(zmax)
    assert (depth >= -1e-12).all() and (depth <= alpha * zmax + ztol).all()


def check_against_the_reference(scene, pixels, tol, depth_atol):
    """The render of a float64 scene: its invariants, the long-double reference within ``tol``
    (depth: absolute ``depth_atol``), and finite gradients of every output."""
    result = render_scene(scene, pixels)
    check_invariants(result, scene)
    depth, features, alpha = reference_of(scene, pixels)
    np.testing.assert_allclose(result.alpha.numpy(), alpha, atol=tol, rtol=tol)
    np.testing.assert_allclose(result.features.numpy(), features, atol=tol, rtol=tol)
    np.testing.assert_allclose(result.depth.numpy(), depth, atol=depth_atol, rtol=tol)
    leaves = {n: t.clone().requires_grad_(True) for n, t in scene.items()}
    out = render_scene(leaves, pixels)
    loss = out.depth.sum() + out.features.square().sum() + out.alpha.sum()
    grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
    assert all_finite(*grads)


@HARD
@given(gaussians=st.lists(gaussian, min_size=1, max_size=6), coincident=st.booleans(),
       first_opaque=st.booleans())
def test_random_extreme_scenes_match_the_long_double_reference(gaussians, coincident,
                                                               first_opaque):
    scene = scene_tensors(gaussians, coincident, torch.float64, first_opaque)
    pixels = pixels_for(scene["means"], torch.float64)
    check_against_the_reference(scene, pixels, tol=1e-8, depth_atol=1e-7)


@HARD
@given(gaussians=st.lists(gaussian, min_size=1, max_size=6), coincident=st.booleans(),
       first_opaque=st.booleans())
def test_random_extreme_scenes_in_float32(gaussians, coincident, first_opaque):
    scene = scene_tensors(gaussians, coincident, torch.float32, first_opaque)
    pixels = pixels_for(scene["means"], torch.float32)
    result = render_scene(scene, pixels)
    check_invariants(result, scene)
    depth, features, alpha = reference_of(scene, pixels)
    # float32 rounding of 1e3 m splats (1e11 px^2 covariances): measured < 2e-4 here; a pair
    # within float32 rounding of the 1/255 alpha cut may flip, so the tolerance is 1/255
    np.testing.assert_allclose(result.alpha.numpy(), alpha, atol=1 / 255, rtol=0)
    np.testing.assert_allclose(result.depth.numpy(), depth, atol=30 / 255, rtol=0)
    leaves = {n: t.clone().requires_grad_(True) for n, t in scene.items()}
    out = render_scene(leaves, pixels)
    loss = out.depth.sum() + out.features.square().sum() + out.alpha.sum()
    assert all_finite(*torch.autograd.grad(loss, list(leaves.values()), allow_unused=True))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_two_opaque_gaussians_tie_on_the_transmittance_cut(dtype):
    """Opacity >= 0.99 is capped at alpha 0.99, so two such splats at one pixel leave
    T = 0.01^2 = 1e-4, exactly the cut. Resolved as gsplat does (stop when T <= 1e-4, the
    stopping splat excluded), in float32 and float64 alike (not by rounding luck): the
    second splat adds nothing, the third neither, and their gradients are zero."""
    scene = {"means": torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 5.0], [0.0, 0.0, 6.0]]),
             "scales": torch.full((3, 3), 0.3), "rotations": torch.tensor([[1.0, 0, 0, 0]] * 3),
             "opacities": torch.tensor([1.0, 0.995, 1.0]),
             "features": torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])}
    scene = {k: v.to(dtype).requires_grad_(True) for k, v in scene.items()}
    pixels = torch.tensor([[176.0, 64.0], [176.3, 64.2]], dtype=dtype)
    out = render_scene(scene, pixels)
    torch.testing.assert_close(out.alpha, torch.full((2,), 0.99, dtype=dtype))
    torch.testing.assert_close(out.depth, torch.full((2,), 0.99 * 4.0, dtype=dtype))
    grads = torch.autograd.grad(out.features.sum() + out.depth.sum(), scene["features"])
    assert grads[0][1:].abs().max() == 0


@FEW
@given(n=st.integers(1000, 4000),
       opacity=st.sampled_from([0.005, 0.02, 0.98]) | st.floats(0.004, 0.98),
       same_depth=st.booleans())
def test_thousands_of_gaussians_in_one_pixel(n, opacity, same_depth):
    """n Gaussians on the optical axis, all at one depth (ties: index order) or spread in
    depth; the pixel at their centre composites them until T would reach 1e-4."""
    z = torch.full((n,), 10.0, dtype=torch.float64) if same_depth else \
        torch.linspace(2.0, 60.0, n, dtype=torch.float64)
    g = torch.Generator().manual_seed(n)
    scene = {"means": torch.stack([torch.zeros(n, dtype=torch.float64),
                                   torch.zeros(n, dtype=torch.float64), z], -1),
             "scales": torch.full((n, 3), 0.3, dtype=torch.float64),
             "rotations": torch.randn(n, 4, generator=g, dtype=torch.float64),
             "opacities": torch.full((n,), opacity, dtype=torch.float64),
             "features": torch.rand(n, 3, generator=g, dtype=torch.float64)}
    pixels = torch.tensor([[176.0, 64.0], [176.5, 64.5], [200.0, 80.0]], dtype=torch.float64)
    check_against_the_reference(scene, pixels, tol=1e-9, depth_atol=1e-8)


@FEW
@given(where=st.sampled_from(["behind", "on the near plane", "outside the image",
                              "transparent", "mixed"]), n=st.integers(1, 50))
def test_nothing_in_view_renders_exact_zeros_with_zero_gradients(where, n):
    g = torch.Generator().manual_seed(n)
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) * 4 - 2
    opacities = torch.full((n,), 0.9, dtype=torch.float64)
    kind = [where] * n if where != "mixed" else \
        [["behind", "on the near plane", "outside the image", "transparent"][i % 4]
         for i in range(n)]
    for i, k in enumerate(kind):
        if k == "behind":
            means[i, 2] = -abs(means[i, 2]) - 0.1
        elif k == "on the near plane":
            means[i, 2] = 0.05                  # z <= near is culled (near = 0.05)
        elif k == "outside the image":
            means[i] = torch.tensor([50.0, 0.0, 1.0], dtype=torch.float64)  # 12500 px right
        else:
            means[i, 2] = 5.0
            opacities[i] = 0.0
    scene = {"means": means.requires_grad_(True),
             "scales": torch.full((n, 3), 0.1, dtype=torch.float64, requires_grad=True),
             "rotations": torch.randn(n, 4, generator=g, dtype=torch.float64,
                                      requires_grad=True),
             "opacities": opacities.requires_grad_(True),
             "features": torch.rand(n, 3, generator=g, dtype=torch.float64, requires_grad=True)}
    pixels = pixels_for(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), torch.float64)
    out = render_scene(scene, pixels)
    assert out.alpha.abs().max() == 0 and out.depth.abs().max() == 0
    assert out.features.abs().max() == 0
    grads = torch.autograd.grad(out.depth.sum() + out.alpha.sum(), list(scene.values()),
                                allow_unused=True)
    assert all(g is None or g.abs().max() == 0 for g in grads)


GRADCHECK_CASES = {
    # name: (means, scales, rotations, opacities, inputs checked)
    "very flat": ([[0.1, 0.0, 4.0], [0.0, 0.1, 5.0]], [[1.0, 0.5, 1e-4], [1e-4, 0.6, 0.8]],
                  [[0.9, 0.3, -0.2, 0.1], [0.2, 0.9, 0.1, 0.3]], [0.6, 0.7], "all"),
    "needle": ([[0.05, 0.02, 4.0]], [[1e-6, 1e-6, 2.0]], [[0.8, 0.4, 0.4, 0.2]], [0.8], "all"),
    "tiny (blur only)": ([[0.0, 0.0, 4.0]], [[1e-6, 1e-6, 1e-6]], [[1.0, 0, 0, 0]], [0.7],
                         "all"),
    "huge and near": ([[0.0, 0.0, 2.0], [0.02, 0.0, 3.0]], [[1e3, 1e3, 1e3], [0.3, 0.3, 0.3]],
                      [[1.0, 0, 0, 0], [0.9, 0.1, 0.2, 0.3]], [0.3, 0.5], "all"),
    "opacity 1 off centre": ([[0.0, 0.0, 4.0]], [[0.2, 0.2, 0.2]], [[1.0, 0, 0, 0]], [1.0],
                             "all"),
    # the identity rule is a jump at |q| = 1e-12 (by design), so rotations are left out
    "zero and denormal quaternions": ([[0.0, 0.0, 4.0], [0.05, 0.0, 5.0]],
                                      [[0.5, 0.2, 0.3], [0.3, 0.5, 0.2]],
                                      [[0.0, 0, 0, 0], [1e-300, 0, 0, 0]], [0.5, 0.6],
                                      "no rotations"),
    # depth sorting is a jump at equal depths (as in every splatting renderer), so the
    # means of coincident Gaussians are left out; everything else is smooth there
    "coincident": ([[0.0, 0.0, 4.0], [0.0, 0.0, 4.0], [0.0, 0.0, 4.0]],
                   [[0.3, 0.2, 0.3], [0.2, 0.4, 0.2], [0.5, 0.1, 0.1]],
                   [[1.0, 0, 0, 0], [0.9, 0.1, 0.2, 0.3], [0.3, 0.3, 0.9, 0.1]],
                   [0.4, 0.5, 0.6], "no means"),
}


@pytest.mark.parametrize("name", sorted(GRADCHECK_CASES))
def test_gradcheck_float64_on_extreme_small_scenes(name):
    means, scales, rotations, opacities, which = GRADCHECK_CASES[name]
    tensors = [torch.tensor(v, dtype=torch.float64) for v in
               (means, scales, rotations, opacities)]
    g = len(means)
    tensors.append(torch.linspace(0.2, 0.9, g * 3, dtype=torch.float64).view(g, 3))
    # pixels around the first centre, off the exact centre (alpha of opacity 1 < 0.99 there;
    # the blur-only splat is ~1 px wide, so its pixels are closer)
    c = 250.0 * tensors[0][0, :2] / tensors[0][0, 2] + torch.tensor([176.0, 64.0],
                                                                     dtype=torch.float64)
    offsets = [[1.3, 0.7], [-2.1, 1.6], [3.2, -2.4]]
    if name == "tiny (blur only)":
        offsets = [[0.3, 0.2], [-0.4, 0.3], [0.2, -0.5]]
    pixels = c + torch.tensor(offsets, dtype=torch.float64)
    cam, k = torch.eye(4, dtype=torch.float64), torch.tensor(K, dtype=torch.float64)
    skip = {"no rotations": 2, "no means": 0}.get(which)
    inputs = [t.clone().requires_grad_(i != skip) for i, t in enumerate(tensors)]

    def fn(*args):
        r = render_gaussians(*args, cam, k, pixels, HW)
        return r.depth, r.features, r.alpha

    out = fn(*inputs)
    assert (out[2] > 0.05).all()          # every pixel is covered: the check is not vacuous
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-6, rtol=1e-5)


def test_quaternion_normalisation_extremes():
    q = torch.tensor([list(v) for v in QUATERNIONS.values()] + [[3e38, 0, 0, -3e38]],
                     dtype=torch.float64)
    unit = normalise_quaternions(q)
    np.testing.assert_allclose(unit.norm(dim=-1).numpy(), 1.0, atol=1e-15)
    huge = np.array([1e20, -3e19, 2e19, 1e20])
    np.testing.assert_allclose(unit[3].numpy(), huge / np.linalg.norm(huge), rtol=1e-15)
    huge32 = normalise_quaternions(torch.tensor([[1e20, 1e20, 0, 0]]))
    torch.testing.assert_close(huge32, torch.tensor([[0.5 ** 0.5, 0.5 ** 0.5, 0, 0]]))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_phi_mlps_on_extreme_means_and_queries(dtype):
    """Phi_s, Phi_r, Phi_sigma: scales stay in [MIN_SCALE, MAX_SCALE], rotations unit,
    opacities in [0, 1], all finite with finite gradients, for means 1e6 m outside the grid
    and query features of 1e4 (a diverging layer)."""
    torch.manual_seed(0)
    phi = GaussianAttributes(32, (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4)).to(dtype)
    means = torch.tensor([[[[0.0, 0.0, 0.0], [1e6, -1e6, 1e6], [-40.0, -40.0, -1.0],
                            [math.ldexp(1, -1074) if dtype == torch.float64 else 1e-45, 0, 0]]]],
                         dtype=dtype, requires_grad=True)
    query = (torch.randn(1, 1, 32, dtype=dtype) * 1e4).requires_grad_(True)
    scales, rotations, opacities = phi(means, query)
    assert all_finite(scales, rotations, opacities)
    assert (scales >= MIN_SCALE).all() and (scales <= MAX_SCALE).all()
    torch.testing.assert_close(rotations.norm(dim=-1), torch.ones(1, 1, 4, dtype=dtype))
    assert (opacities >= 0).all() and (opacities <= 1).all()
    loss = scales.sum() + rotations.sum() + opacities.sum()
    assert all_finite(*torch.autograd.grad(loss, [means, query, *phi.parameters()]))
