"""Reduced precision: the decoder and the renderer under CPU autocast (bfloat16 and float16),
no overflow to inf, agreement with float32 within the tolerances below (measured on this
tiny model over 3 seeds; the measured maxima are in docs/HARD_CASES.md).

The geometry of the 4D sampling (warp, projection) and the whole renderer are computed in
float32 whatever autocast is active, so they agree *exactly* with float32; the rest of the
decoder (linear layers, attention, grid_sample of half-precision features) runs in half
precision and agrees within the tolerances.
"""
import math

import pytest
import torch

from odg_ros.losses import ODGCriterion
from odg_ros.network import ODG
from odg_ros.network.postprocess import occupancy_grid
from odg_ros.network.sampling import first_visible_camera, warp_points
from odg_ros.render import render_cameras
from odg_ros.nuscenes_cameras import ring_ego2img

from testing.hard_cases import all_finite
from testing.helpers import model_inputs, tiny_config
from testing.losses import make_batch
from testing.render import random_scene

# max |half - float32| over every layer (random weights, random images). Measured maxima
# over 3 seeds: bf16 means 0.011 m, logits 0.074, scales 0.0062 m, rotations 0.024,
# opacities 0.0037, boxes 0.0046, box logits 0.027; fp16 means 0.0008 m, logits 0.0052,
# scales 0.0009 m, rotations 0.0007, opacities 0.0003, boxes 0.0005, box logits 0.0043.
# Tolerances: about 4x those maxima. (Of 50 draws of the model's weights, one gave fp16 errors
# about 6x the others from the third layer on, means 0.005 m: these bounds fit the typical
# draw, not every one.)
TOLERANCE = {
    torch.bfloat16: {"means": 0.05, "logits": 0.3, "scales": 0.025, "rotations": 0.1,
                     "opacities": 0.015, "boxes": 0.02, "box_logits": 0.1},
    torch.float16: {"means": 0.004, "logits": 0.02, "scales": 0.004, "rotations": 0.003,
                    "opacities": 0.0015, "boxes": 0.002, "box_logits": 0.02},
}
FIELDS = tuple(TOLERANCE[torch.bfloat16])


@pytest.fixture(scope="module")
def model_and_inputs():
    torch.manual_seed(0)
    cfg = tiny_config(image_size=(32, 88))
    model = ODG(cfg).eval()
    # The box residual starts at zero: give it something to round, from a generator of its
    # own so that the draw does not move when the model gains a module.
    box_weights = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for layer in model.decoder.layers:
            torch.nn.init.normal_(layer.boxes.reg[-1].weight, std=0.05, generator=box_weights)
    return cfg, model, model_inputs(cfg)


def layer_errors(reference, output):
    errors = {name: 0.0 for name in FIELDS}
    for a, b in zip(reference.layers, output.layers):
        for name in FIELDS:
            x, y = getattr(a, name), getattr(b, name)
            if x is not None:
                errors[name] = max(errors[name], float((x.float() - y.float()).abs().max()))
    return errors


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16], ids=["bf16", "fp16"])
def test_decoder_under_autocast_agrees_with_float32(model_and_inputs, dtype):
    cfg, model, inputs = model_and_inputs
    with torch.no_grad():
        reference = model(*inputs, gaussian_attributes=True)
        with torch.autocast("cpu", dtype=dtype):
            output = model(*inputs, gaussian_attributes=True)
    for layer in output.layers:
        assert all_finite(*(getattr(layer, n) for n in FIELDS))
    errors = layer_errors(reference, output)
    for name, error in errors.items():
        assert error <= TOLERANCE[dtype][name], (name, error)
    # the post-processed grid is computed in float32 from the half-precision scores
    labels, confidence = occupancy_grid(output, cfg)
    assert labels.shape == (1, *cfg.grid_shape)


@pytest.mark.parametrize("dtype,images", [
    (torch.float16, "saturated white"), (torch.float16, "black"),
    (torch.float16, "noise x 30"), (torch.bfloat16, "noise x 30")])
def test_decoder_under_autocast_does_not_overflow_on_extreme_images(model_and_inputs, dtype,
                                                                    images):
    """Normalised images of a saturated sensor (255 -> ~+2.6), of a black one (~-2.1) and
    of noise 30x the normal range: no inf or NaN anywhere in half precision (float16 tops
    out at 65504; bfloat16 has float32's range, so it gets the harshest case only)."""
    cfg, model, (x, e2i, warp, dt) = model_and_inputs
    if images == "saturated white":
        x = torch.full_like(x, 2.64)
    elif images == "black":
        x = torch.full_like(x, -2.12)
    else:
        x = x * 30.0
    with torch.no_grad(), torch.autocast("cpu", dtype=dtype):
        output = model(x, e2i, warp, dt, gaussian_attributes=True)
    for layer in output.layers:
        assert all_finite(*(getattr(layer, n) for n in FIELDS))


def test_training_step_under_bf16_autocast_has_finite_loss_and_gradients(model_and_inputs):
    """The trainer's CUDA recipe (bf16 autocast forward, float32 losses) on the CPU."""
    cfg, model, inputs = model_and_inputs
    model.train()
    try:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            output = model(*inputs, gaussian_attributes=True)
        batch = make_batch()
        B = 1
        batch = {k: (v[:B] if torch.is_tensor(v) else v[:B]) for k, v in batch.items()}
        N = cfg.num_cams
        batch["cam_from_ego"] = torch.eye(4).expand(B, N, 4, 4).clone()
        batch["intrinsics"] = torch.tensor([[40.0, 0, 44], [0, 40.0, 16], [0, 0, 1]]).expand(
            B, N, 3, 3).clone()
        batch["render_targets"] = [[torch.tensor([[44.0, 16.0, 5.0, 4.0]])] * N]
        losses = ODGCriterion(cfg, render_pixels_per_camera=8)(output, batch)
        assert all(torch.isfinite(v).all() for v in losses.values())
        model.zero_grad(set_to_none=True)
        losses["loss"].backward()
        assert all_finite(*(p.grad for p in model.parameters() if p.grad is not None))
    finally:
        model.eval()
        model.zero_grad(set_to_none=True)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16], ids=["bf16", "fp16"])
def test_sampling_geometry_is_exact_under_autocast(dtype):
    """Before the fix, bf16 autocast ran the warp and projection matmuls in bf16: sampling
    points up to 5.9 px off across a 704 px image (0.9 px in fp16)."""
    g = torch.Generator().manual_seed(0)
    H, W = 256, 704
    e2i = ring_ego2img((H, W), 2, 6)
    points = (torch.rand(1, 500, 1, 3, generator=g) - 0.5) * torch.tensor([80.0, 80.0, 6.0])
    warp = torch.eye(4).repeat(1, 2, 1, 1)
    warp[0, 1, 0, 3] = 5.0
    dt = torch.tensor([[0.0, 0.5]])
    velocity = torch.randn(1, 500, 2, generator=g) * 10
    expected = first_visible_camera(warp_points(points, velocity, dt, warp), e2i, (H, W))
    with torch.autocast("cpu", dtype=dtype):
        got = first_visible_camera(warp_points(points, velocity, dt, warp), e2i, (H, W))
    for a, b in zip(expected, got):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16], ids=["bf16", "fp16"])
def test_renderer_under_autocast_equals_float32(dtype):
    """Before the fix the renderer crashed under bf16 autocast (no bf16 sparse CPU kernel)."""
    scene, cam, k, pixels = random_scene(7, 300, 300, dtype=torch.float32)
    args = (scene["means"], scene["scales"], scene["rotations"], scene["opacities"],
            scene["features"], cam[None], k[None], [pixels], (128, 352))
    expected = render_cameras(*args)[0]
    with torch.autocast("cpu", dtype=dtype):
        got = render_cameras(*args)[0]
    for a, b in zip(expected, got):
        assert b.dtype == torch.float32 and torch.equal(a, b)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16], ids=["bf16", "fp16"])
def test_half_precision_gaussians_render_in_float32(dtype):
    """Half-precision Gaussians render as their float32 values would (only the rounding of
    the inputs differs), with float32 outputs and gradients."""
    scene, cam, k, pixels = random_scene(3, 200, 200, dtype=torch.float32)
    half = {n: t.to(dtype).requires_grad_(True) for n, t in scene.items()}
    rounded = {n: t.detach().float() for n, t in half.items()}
    names = ("means", "scales", "rotations", "opacities", "features")
    got = render_cameras(*(half[n] for n in names), cam[None], k[None], [pixels], (128, 352))[0]
    expected = render_cameras(*(rounded[n] for n in names), cam[None], k[None], [pixels],
                              (128, 352))[0]
    for a, b in zip(expected, got):
        assert b.dtype == torch.float32 and torch.equal(a, b)
    grads = torch.autograd.grad(got.depth.sum() + got.alpha.sum(), [half[n] for n in names])
    assert all(g.dtype == dtype for g in grads) and all_finite(*grads)
    assert math.isfinite(float(got.depth.detach().sum()))


def test_bf16_on_a_cpu_without_native_bf16_is_called_slow(monkeypatch):
    """bf16 autocast on a CPU without bf16 kernels costs ~7x fp32 (measured, AVX2 EPYC): the node
    and odg bench say so instead of silently running slower than the default."""
    from odg_ros.network import precision

    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: False)
    assert "no native bf16 kernels" in precision.slow_precision_warning("bf16", "cpu")
    assert precision.slow_precision_warning("fp32", "cpu") is None
    assert precision.slow_precision_warning("bf16", "cuda") is None
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: True)
    assert precision.slow_precision_warning("bf16", "cpu") is None


def test_odg_bench_reports_the_slow_precision(monkeypatch, capsys, tmp_path):
    import json

    from odg_ros import commands
    from odg_ros.network import precision

    from testing.helpers import write_tiny_checkpoint

    checkpoint = write_tiny_checkpoint(tmp_path / "tiny.pt", image_size=(32, 88), num_frames=2)
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: False)
    assert commands.main(["bench", "--checkpoint", str(checkpoint), "--precision", "bf16",
                     "--iters", "1", "--warmup", "0", "--json"]) == 0
    out, err = capsys.readouterr()
    assert "odg bench: bf16 on this CPU has no native bf16 kernels" in err
    assert any("no native bf16 kernels" in w for w in json.loads(out)["warnings"])
