"""Rendering loss (paper Eq. 6 and 11): each layer's Gaussians are splatted into the current
frame's cameras at the pixels that carry a projected LiDAR point, and the rendered depth and
semantics are compared with the LiDAR depth (L1) and label (cross-entropy).

Choices the paper leaves open, and ours:
* Semantic colour of a Gaussian: c_i = softmax over its 17 class logits. The paper asks for a
  "semantic probability" c_i in [0, 1]^C; softmax makes it a distribution, so the rendered
  S_p = sum_i T_i alpha_i c_i is a sub-distribution whose mass is the pixel's opacity
  (sum_c S_p,c = alpha_p <= 1). The logits stay the sigmoid scores of the focal loss; softmax is
  shift-invariant, so this term only asks for the right class to win, it does not move the
  absolute sigmoid calibration the focal loss sets.
* CE on a sub-distribution: -log(S_p,label + 1e-6). Not renormalised by alpha_p, so a LiDAR
  pixel also asks for opacity there (it is a surface); a pixel no Gaussian reaches costs
  -log(1e-6) = 13.8 with zero gradient (nothing to move).
* Depth: the renderer's depth as it is (alpha-composited, paper Eq. 6), L1 in metres.
* Normalisers: the numbers of supervised pixels (depth) and of pixels with a valid label 0..16
  (semantics) over the batch; labels outside 0..16 (free 17, ignore values) get depth only.
* Pixels: at most ``max_pixels`` per camera, a random subset drawn once per criterion call from
  a seeded generator and shared by all layers (rendering cost grows with it; CPU training needs
  few).
* Layer weights: lambda_l = 0.05 for the first and the last layer, 0.01 for the others.

The renderer is ``odg_ros.render.render_cameras`` -- ``render_gaussians`` for the N cameras of a
sample in one pass (gsplat conventions, docs/architecture.md sec. 5); a callable with its signature
``(means, scales, rotations, opacities, features, cam_from_ego [N,4,4], intrinsics [N,3,3],
pixels N x [P_n,2], image_hw, near=) -> N x RenderResult(depth, features, alpha)`` can be
passed instead.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch

RENDER_WEIGHT_OUTER = 0.05   # layers 1 and L
RENDER_WEIGHT_INNER = 0.01   # the others
SEMANTIC_EPS = 1e-6
NEAR_PLANE = 0.05


def render_layer_weights(num_layers: int) -> list[float]:
    """lambda_l for l = 1..L (paper: 0.05 for l in {1, L}, 0.01 otherwise)."""
    return [RENDER_WEIGHT_OUTER if l in (0, num_layers - 1) else RENDER_WEIGHT_INNER
            for l in range(num_layers)]


def default_renderer() -> Callable:
    from ..render import render_cameras
    return render_cameras


def sample_render_targets(render_targets: Sequence[Sequence[torch.Tensor]], max_pixels: int,
                          generator: torch.Generator | None = None) -> list[list[torch.Tensor]]:
    """B x N x [P, 4] (u, v, depth, label) -> same with at most max_pixels rows per camera,
    a uniformly random subset (order kept). max_pixels <= 0 keeps everything."""
    out = []
    for per_sample in render_targets:
        cams = []
        for t in per_sample:
            if t.dim() != 2 or t.shape[1] != 4:
                raise ValueError(f"render targets must be [P, 4], got {tuple(t.shape)}")
            if 0 < max_pixels < t.shape[0]:
                keep = torch.randperm(t.shape[0], generator=generator)[:max_pixels]
                t = t[keep.sort().values.to(t.device)]
            cams.append(t)
        out.append(cams)
    return out


@dataclass
class RenderLossResult:
    depth: torch.Tensor       # scalar, mean |D_hat - D| over supervised pixels (m)
    semantic: torch.Tensor    # scalar, mean CE over labelled pixels
    num_pixels: int
    num_labelled: int | torch.Tensor   # a device count (0-dim): reading it would wait for it


def render_loss(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor,
                opacities: torch.Tensor, logits: torch.Tensor,
                render_targets: Sequence[Sequence[torch.Tensor]], cam_from_ego: torch.Tensor,
                intrinsics: torch.Tensor, image_hw: tuple[int, int],
                renderer: Callable | None = None, near: float = NEAR_PLANE) -> RenderLossResult:
    """Depth L1 + semantic CE of one layer.

    means/scales [B, G, 3], rotations [B, G, 4] (w, x, y, z), opacities [B, G], logits [B, G, C];
    render_targets B x N x [P, 4] (u, v, depth m, label) in network-input pixels;
    cam_from_ego [B, N, 4, 4], intrinsics [B, N, 3, 3] (network input).
    """
    B, G = means.shape[:2]
    if (scales.shape != (B, G, 3) or rotations.shape != (B, G, 4) or opacities.shape != (B, G)
            or logits.shape[:2] != (B, G)):
        raise ValueError("Gaussian attributes must be [B, G, ...] with matching B, G: means "
                         f"{tuple(means.shape)} scales {tuple(scales.shape)} rotations "
                         f"{tuple(rotations.shape)} opacities {tuple(opacities.shape)} "
                         f"logits {tuple(logits.shape)}")
    if len(render_targets) != B or cam_from_ego.shape[:2] != intrinsics.shape[:2] \
            or cam_from_ego.shape[0] != B:
        raise ValueError("render_targets / cam_from_ego / intrinsics do not match the batch")
    renderer = renderer or default_renderer()
    num_classes = logits.shape[-1]
    probs = torch.softmax(logits.float(), dim=-1)
    depth_sum = sem_sum = probs.new_zeros(())
    num_pixels = num_labelled = 0
    for b in range(B):
        if len(render_targets[b]) != cam_from_ego.shape[1]:
            raise ValueError(f"sample {b}: {len(render_targets[b])} render target sets for "
                             f"{cam_from_ego.shape[1]} cameras")
        targets = [t.to(means.device, torch.float32) for t in render_targets[b]]
        if any(t.dim() != 2 or t.shape[1] != 4 for t in targets):
            raise ValueError(f"sample {b}: render targets must be [P, 4] (u, v, depth, label)")
        target = torch.cat(targets) if targets else means.new_zeros(0, 4)
        if target.shape[0] == 0:
            continue
        if not torch.isfinite(target).all():
            raise ValueError(f"sample {b}: non-finite render target")
        results = renderer(means[b].float(), scales[b].float(), rotations[b].float(),
                           opacities[b].float(), probs[b], cam_from_ego[b].float(),
                           intrinsics[b].float(), [t[:, :2] for t in targets], tuple(image_hw),
                           near=near)
        depth = torch.cat([r.depth for r in results])
        features = torch.cat([r.features for r in results])
        depth_sum = depth_sum + (depth - target[:, 2]).abs().sum()
        num_pixels += target.shape[0]
        labels = target[:, 3].round().long()
        labelled = (labels >= 0) & (labels < num_classes)
        # every pixel's mass at its (clamped) label, the unlabelled ones weighted 0: the
        # number of labelled pixels stays on the device
        mass = features.gather(1, labels.clamp(0, num_classes - 1)[:, None])[:, 0]
        sem_sum = sem_sum - torch.where(labelled, torch.log(mass + SEMANTIC_EPS), 0).sum()
        num_labelled = num_labelled + labelled.sum()
    return RenderLossResult(depth=depth_sum / max(num_pixels, 1),
                            semantic=sem_sum / torch.as_tensor(num_labelled).clamp(min=1),
                            num_pixels=num_pixels, num_labelled=num_labelled)
