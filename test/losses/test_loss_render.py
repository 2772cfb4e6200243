"""Rendering loss: plumbing against a hand-checkable stand-in renderer, then the real splatting
renderer (odg_ros.render) on a single Gaussian in front of a camera."""
import math
from typing import NamedTuple

import pytest
import torch

from odg_ros.losses.render_loss import (SEMANTIC_EPS, one_call_per_scene, render_layer_weights,
                                        render_loss, sample_render_targets)

H, W = 32, 64
K = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 16.0], [0, 0, 1]])
# OpenCV camera at the ego origin looking along ego +x (cam x = -ego y, cam y = -ego z).
CAM_FROM_EGO = torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]])


class Result(NamedTuple):
    depth: torch.Tensor
    features: torch.Tensor
    alpha: torch.Tensor


def half_of_first_gaussian(means, scales, rotations, opacities, features, cam_from_ego,
                           intrinsics, pixels, image_hw, near=0.05):
    """Stand-in renderer with the render_cameras signature: every pixel sees half of
    Gaussian 0 (depth 0.5 * its z, features 0.5 * its features)."""
    assert cam_from_ego.shape == (len(pixels), 4, 4) and intrinsics.shape == (len(pixels), 3, 3)
    assert tuple(image_hw) == (H, W)
    out = []
    for p in pixels:
        n = p.shape[0]
        out.append(Result(depth=(0.5 * means[0, 2]).expand(n),
                          features=(0.5 * features[0]).expand(n, -1),
                          alpha=torch.full((n,), 0.5)))
    return out


def gaussians(B, G, C=17, requires_grad=True):
    means = torch.randn(B, G, 3)
    means[..., 0] = means[..., 0].abs() + 5
    scales = torch.full((B, G, 3), 0.5)
    rotations = torch.zeros(B, G, 4)
    rotations[..., 0] = 1
    opacities = torch.full((B, G), 0.8)
    logits = torch.randn(B, G, C)
    tensors = [means, scales, rotations, opacities, logits]
    if requires_grad:
        for t in tensors:
            t.requires_grad_(True)
    return tensors


def test_layer_weights_paper():
    assert render_layer_weights(6) == [0.05, 0.01, 0.01, 0.01, 0.01, 0.05]
    assert render_layer_weights(1) == [0.05]


def test_pixel_subsampling_bounded_seeded_and_ordered():
    rows = torch.arange(100, dtype=torch.float32)[:, None].repeat(1, 4)
    targets = [[rows, rows[:5], rows[:0]]]
    a = sample_render_targets(targets, 10, torch.Generator().manual_seed(3))
    b = sample_render_targets(targets, 10, torch.Generator().manual_seed(3))
    c = sample_render_targets(targets, 10, torch.Generator().manual_seed(4))
    assert [t.shape[0] for t in a[0]] == [10, 5, 0]
    assert torch.equal(a[0][0], b[0][0]) and not torch.equal(a[0][0], c[0][0])
    kept = a[0][0][:, 0]
    assert torch.all(kept[1:] > kept[:-1])                     # a subset, order kept
    assert sample_render_targets(targets, 0)[0][0].shape[0] == 100
    with pytest.raises(ValueError, match=r"\[P, 4\]"):
        sample_render_targets([[torch.zeros(3, 3)]], 10)


def test_render_loss_hand_checked_with_stand_in_renderer():
    means, scales, rotations, opacities, logits = gaussians(2, 3)
    # (u, v, depth, label); label 17 (free) and 255 get depth supervision only
    targets = [
        [torch.tensor([[1.0, 2.0, 4.0, 4.0], [3.0, 4.0, 9.0, 17.0]]), torch.zeros(0, 4)],
        [torch.tensor([[5.0, 6.0, 2.0, 0.0]]), torch.tensor([[7.0, 8.0, 1.0, 255.0]])],
    ]
    cams = CAM_FROM_EGO.expand(2, 2, 4, 4)
    ks = K.expand(2, 2, 3, 3)
    res = render_loss(means, scales, rotations, opacities, logits, targets, cams, ks, (H, W),
                      renderer=one_call_per_scene(half_of_first_gaussian))
    z = [0.5 * means[b, 0, 2].item() for b in range(2)]
    depth = (abs(z[0] - 4) + abs(z[0] - 9) + abs(z[1] - 2) + abs(z[1] - 1)) / 4
    probs = torch.softmax(logits.detach()[:, 0], -1)
    sem = (-math.log(0.5 * probs[0, 4].item() + SEMANTIC_EPS)
           - math.log(0.5 * probs[1, 0].item() + SEMANTIC_EPS)) / 2
    assert res.num_pixels == 4 and res.num_labelled == 2
    assert res.depth.item() == pytest.approx(depth, rel=1e-5)
    assert res.semantic.item() == pytest.approx(sem, rel=1e-5)
    (res.depth + res.semantic).backward()
    assert torch.isfinite(means.grad).all() and torch.isfinite(logits.grad).all()
    assert means.grad[:, 0, 2].abs().min() > 0


def test_no_lidar_pixel_is_zero_not_nan():
    means, scales, rotations, opacities, logits = gaussians(1, 2)
    res = render_loss(means, scales, rotations, opacities, logits,
                      [[torch.zeros(0, 4), torch.zeros(0, 4)]], CAM_FROM_EGO.expand(1, 2, 4, 4),
                      K.expand(1, 2, 3, 3), (H, W), renderer=one_call_per_scene(half_of_first_gaussian))
    assert res.depth.item() == 0 and res.semantic.item() == 0
    assert res.num_pixels == 0 and res.num_labelled == 0


def test_bad_targets_raise():
    means, scales, rotations, opacities, logits = gaussians(1, 2, requires_grad=False)
    bad = torch.tensor([[1.0, 2.0, float("nan"), 3.0]])
    with pytest.raises(ValueError, match="non-finite"):
        render_loss(means, scales, rotations, opacities, logits, [[bad]],
                    CAM_FROM_EGO.expand(1, 1, 4, 4), K.expand(1, 1, 3, 3), (H, W),
                    renderer=one_call_per_scene(half_of_first_gaussian))
    with pytest.raises(ValueError, match="cameras"):
        render_loss(means, scales, rotations, opacities, logits, [[bad, bad]],
                    CAM_FROM_EGO.expand(1, 1, 4, 4), K.expand(1, 1, 3, 3), (H, W),
                    renderer=one_call_per_scene(half_of_first_gaussian))


def test_gaussians_of_another_batch_size_raise():
    means, scales, rotations, opacities, logits = gaussians(2, 3, requires_grad=False)
    target = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    with pytest.raises(ValueError, match="Gaussian attributes must be"):
        render_loss(means[:1], scales, rotations, opacities, logits, [[target], [target]],
                    CAM_FROM_EGO.expand(2, 1, 4, 4), K.expand(2, 1, 3, 3), (H, W),
                    renderer=one_call_per_scene(half_of_first_gaussian))
    with pytest.raises(ValueError, match="Gaussian attributes must be"):
        render_loss(means[:1], scales[:1], rotations[:1], opacities[:1], logits[:1],
                    [[target], [target]], CAM_FROM_EGO.expand(2, 1, 4, 4),
                    K.expand(2, 1, 3, 3), (H, W), renderer=one_call_per_scene(half_of_first_gaussian))


# --- the real renderer ------------------------------------------------------------------------

def one_gaussian_scene(opacity=0.9, cls=4):
    means = torch.tensor([[[10.0, 0.0, 0.0]]], requires_grad=True)
    scales = torch.full((1, 1, 3), 1.0, requires_grad=True)
    rotations = torch.tensor([[[1.0, 0.0, 0.0, 0.0]]], requires_grad=True)
    opacities = torch.tensor([[opacity]], requires_grad=True)
    logits = torch.full((1, 1, 17), -5.0)
    logits[0, 0, cls] = 5.0
    logits.requires_grad_(True)
    return means, scales, rotations, opacities, logits


def test_real_renderer_single_gaussian():
    pytest.importorskip("odg_ros.render")
    means, scales, rotations, opacities, logits = one_gaussian_scene()
    # the pixel at the principal point sees the Gaussian's centre: alpha = opacity = 0.9
    target = torch.tensor([[32.0, 16.0, 10.0, 4.0]])
    res = render_loss(means, scales, rotations, opacities, logits, [[target]],
                      CAM_FROM_EGO.expand(1, 1, 4, 4), K.expand(1, 1, 3, 3), (H, W))
    p4 = torch.softmax(logits.detach()[0, 0], -1)[4].item()
    assert res.depth.item() == pytest.approx(10 - 0.9 * 10, abs=1e-3)
    assert res.semantic.item() == pytest.approx(-math.log(0.9 * p4 + SEMANTIC_EPS), abs=1e-4)
    (res.depth + res.semantic).backward()
    for t in (means, scales, rotations, opacities, logits):
        assert torch.isfinite(t.grad).all()
    assert opacities.grad.item() < 0                 # more opacity: closer depth, more mass
    assert logits.grad[0, 0, 4].item() < 0           # the right class is pushed up


def test_real_renderer_pixel_nobody_covers_costs_constant():
    pytest.importorskip("odg_ros.render")
    means, scales, rotations, opacities, logits = one_gaussian_scene()
    target = torch.tensor([[1.0, 1.0, 30.0, 4.0]])              # image corner, far from it
    res = render_loss(means, scales, rotations, opacities, logits, [[target]],
                      CAM_FROM_EGO.expand(1, 1, 4, 4), K.expand(1, 1, 3, 3), (H, W))
    assert res.depth.item() == pytest.approx(30.0, abs=1e-4)
    assert res.semantic.item() == pytest.approx(-math.log(SEMANTIC_EPS), rel=1e-4)
    assert torch.isfinite(res.depth + res.semantic)
