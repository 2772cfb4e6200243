"""The int8 image encoder (network/int8_encoder.py): its outputs against the float encoder's,
the side file of activation ranges (same arithmetic as the calibration, bound to its weights),
and the int8-encoder precision setting."""
import copy
import json

import pytest
import torch
import torch.nn.functional as F

from odg_ros.network import int8_encoder
from odg_ros.network.checkpoint import load_model
from odg_ros.network.precision import precision_context, resolve_precision, slow_precision_warning
from odg_ros.online.step import OnlineStep
from odg_ros.resources import shipped_checkpoint

pytestmark = pytest.mark.skipif(not int8_encoder.int8_available(),
                                reason="this PyTorch build has no x86 quantized engine")

# the shipped encoder on camera-like inputs: int8 levels within 8 % (relative L2) of fp32
TOLERANCE = 0.08


def camera_like(seed, n=2, size=(64, 176)):
    """Normalised images with an image's spatial correlation (upsampled noise + fine grain)."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.randn(n, 3, size[0] // 8, size[1] // 8, generator=g)
    x = F.interpolate(coarse, size=size, mode="bilinear", align_corners=False)
    return (x + 0.2 * torch.randn(n, 3, *size, generator=g)).contiguous(
        memory_format=torch.channels_last)


def relative_errors(reference, levels):
    return [float((r - q).norm() / r.norm()) for r, q in zip(reference, levels)]


@pytest.fixture(scope="module")
def shipped():
    model, cfg = load_model(shipped_checkpoint())
    step = OnlineStep(model, cfg, cfg.num_frames, "cpu", "fp32", visibility=False)
    fingerprint = int8_encoder.encoder_fingerprint(model.backbone, model.neck)
    calibration = [camera_like(seed) for seed in range(3)]
    content = int8_encoder.calibrate(step.backbone, step.neck, calibration, fingerprint)
    return model, cfg, step, fingerprint, content


def test_int8_encoder_is_within_tolerance_of_fp32_and_fails_with_wrong_scales(shipped):
    """Calibrated on some images, scored on others: every FPN level within TOLERANCE of the
    float encoder's. The same check catches a broken quantization: activation ranges a
    quarter of the calibrated ones (clipping) or four times them (coarse steps)."""
    _, _, step, _, content = shipped
    x = camera_like(100)
    with torch.no_grad():
        reference = step.neck(step.backbone(x))
        quantized = int8_encoder.quantized_encoder(step.backbone, step.neck, content["ranges"], x)
        errors = relative_errors(reference, quantized(x))
        assert max(errors) < TOLERANCE, errors
        for factor in (0.25, 4.0):
            wrong = {k: [lo * factor, hi * factor] for k, (lo, hi) in content["ranges"].items()}
            broken = int8_encoder.quantized_encoder(step.backbone, step.neck, wrong, x)
            assert max(relative_errors(reference, broken(x))) > TOLERANCE, factor


def test_ranges_reproduce_the_calibrated_quantization_exactly(shipped, monkeypatch):
    """The side file keeps each histogram observer's chosen range: an encoder built from it
    (on a CPU with VNNI: 8-bit activations, as calibrated) computes bit for bit what the
    calibrated observers' own conversion computes."""
    from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx
    from odg_ros.network import precision
    monkeypatch.setattr(precision, "cpu_has_vnni", lambda: True)
    _, _, step, _, content = shipped
    calibration = [camera_like(seed) for seed in range(3)]
    prepared = prepare_fx(int8_encoder.Encoder(step.backbone, step.neck).eval(),
                          int8_encoder._calibration_mapping(), (calibration[0],))
    x = camera_like(7)
    with torch.no_grad():
        for batch in calibration:
            prepared(batch)
        direct = convert_fx(prepared)(x)
        from_file = int8_encoder.quantized_encoder(step.backbone, step.neck,
                                                   content["ranges"], x)(x)
    assert all(torch.equal(a, b) for a, b in zip(direct, from_file))


def quantized_modules(encoder):
    return {name: m for name, m in encoder.named_modules()
            if type(m).__module__.startswith("torch.ao.nn.quantized")}


def test_stem_stays_float_and_activations_take_7_bits_without_vnni(shipped, monkeypatch):
    """The stem convolution is a float one (its error was the largest of any layer's in
    int8), every other convolution an int8 one. Without VNNI the same ranges are spread over
    7 bits, the output scales twice the 8-bit ones, and the levels stay within tolerance."""
    from odg_ros.network import precision
    _, _, step, _, content = shipped
    x = camera_like(100)
    encoders = {}
    for vnni in (True, False):
        monkeypatch.setattr(precision, "cpu_has_vnni", lambda vnni=vnni: vnni)
        encoders[vnni] = int8_encoder.quantized_encoder(step.backbone, step.neck,
                                                        content["ranges"], x)
    eight = encoders[True]
    assert type(eight.get_submodule("backbone.conv1")) is torch.nn.Conv2d
    convs = {n for n, m in int8_encoder.Encoder(step.backbone, step.neck).named_modules()
             if isinstance(m, torch.nn.Conv2d)} - set(int8_encoder.FLOAT_MODULES)
    assert convs <= set(quantized_modules(eight)), convs - set(quantized_modules(eight))
    seven = quantized_modules(encoders[False])
    for name, module in quantized_modules(eight).items():
        if hasattr(module, "scale"):
            assert seven[name].scale == pytest.approx(module.scale * 255 / 127, rel=1e-5), name
    with torch.no_grad():
        reference = step.neck(step.backbone(x))
        assert max(relative_errors(reference, encoders[False](x))) < TOLERANCE


def test_shipped_ranges_belong_to_the_shipped_checkpoint_and_run_in_the_step(shipped):
    """model/int8 holds the shipped encoder's ranges; the step at int8-encoder loads them and
    its features stay within tolerance of the fp32 step's."""
    model, cfg, fp32_step, fingerprint, _ = shipped
    path = int8_encoder.ranges_path(fingerprint)
    saved = json.loads(path.read_text())
    assert saved["fingerprint"] == fingerprint and saved["images"] >= 100
    step = OnlineStep(model, cfg, cfg.num_frames, "cpu", "int8-encoder", visibility=False)
    assert step.int8_encoder is not None
    x = camera_like(5, n=cfg.num_cams, size=tuple(cfg.image_size))
    with torch.no_grad():
        errors = relative_errors([f[0] for f in fp32_step.features(x)],
                                 [f[0] for f in step.features(x)])
    assert max(errors) < TOLERANCE, errors


def test_ranges_of_other_weights_or_a_missing_file_are_refused(shipped, tmp_path):
    _, _, step, fingerprint, content = shipped
    path = int8_encoder.ranges_path(fingerprint, root=tmp_path)
    path.write_text(json.dumps({**content, "fingerprint": "0" * 16}))
    with pytest.raises(int8_encoder.MissingRanges, match="not the ranges of this encoder"):
        int8_encoder.load_ranges(path, fingerprint)
    with pytest.raises(int8_encoder.MissingRanges, match="no activation ranges"):
        int8_encoder.ranges_path("f" * 16)
    fewer = dict(list(content["ranges"].items())[1:])
    with pytest.raises(int8_encoder.MissingRanges, match="do not match"):
        int8_encoder.quantized_encoder(step.backbone, step.neck, fewer, camera_like(0))
    nan = {k: [float("nan"), v[1]] for k, v in content["ranges"].items()}
    with pytest.raises(int8_encoder.MissingRanges, match="not a finite range"):
        int8_encoder.quantized_encoder(step.backbone, step.neck, nan, camera_like(0))


def test_fingerprint_changes_with_any_weight(shipped):
    model, _, _, fingerprint, _ = shipped
    neck = copy.deepcopy(model.neck)
    assert int8_encoder.encoder_fingerprint(model.backbone, neck) == fingerprint
    with torch.no_grad():
        neck.output[0].bias[0] += 1e-3
    assert int8_encoder.encoder_fingerprint(model.backbone, neck) != fingerprint


def test_int8_encoder_setting_is_cpu_only():
    assert resolve_precision("int8-encoder", "cpu") == "int8-encoder"
    precision_context("int8-encoder", "cpu")
    with pytest.raises(ValueError, match="int8-encoder is for CPU"):
        resolve_precision("int8-encoder", "cuda")
    with pytest.raises(ValueError, match="expected one of"):
        resolve_precision("int4-encoder", "cpu")
    assert resolve_precision("auto", "cpu") != "int8-encoder"        # never picked by auto


def test_int8_encoder_warns_without_vnni(monkeypatch):
    from odg_ros.network import precision
    monkeypatch.setattr(precision, "_cpu_flags", lambda: frozenset({"avx2"}))
    assert "7 bits" in slow_precision_warning("int8-encoder", "cpu")
    monkeypatch.setattr(precision, "_cpu_flags", lambda: frozenset({"avx2", "avx512_vnni"}))
    assert slow_precision_warning("int8-encoder", "cpu") is None
