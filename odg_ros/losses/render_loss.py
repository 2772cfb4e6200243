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

The renderer is ours, ``odg_ros.render`` (gsplat conventions, docs/architecture.md sec. 5):
``render_losses`` draws every layer of every sample in one ``render_scenes`` call. Another
renderer with the signature of ``render_scenes`` can be passed instead (gsplat's,
``render.gsplat_backend.render_scenes_gsplat``), and ``one_call_per_scene`` makes one of a
renderer with the signature of ``render_cameras`` (the N cameras of one scene).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch

from ..transfer import upload

RENDER_WEIGHT_OUTER = 0.05   # layers 1 and L
RENDER_WEIGHT_INNER = 0.01   # the others
SEMANTIC_EPS = 1e-6
NEAR_PLANE = 0.05


def render_layer_weights(num_layers: int) -> list[float]:
    """lambda_l for l = 1..L (paper: 0.05 for l in {1, L}, 0.01 otherwise)."""
    return [RENDER_WEIGHT_OUTER if l in (0, num_layers - 1) else RENDER_WEIGHT_INNER
            for l in range(num_layers)]


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
                keep = keep.sort().values
                # the targets stay where they are: on the host in training, no copy at all
                t = t[keep if keep.device == t.device else upload(keep, t.device)]
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
    A non-finite target raises ValueError (one host read; render_losses leaves it to the caller).
    """
    (result,), targets_finite = render_losses(
        [(means, scales, rotations, opacities, logits)], render_targets, cam_from_ego,
        intrinsics, image_hw, renderer, near)
    if not targets_finite:
        raise ValueError(NONFINITE_TARGET)
    return result


NONFINITE_TARGET = "non-finite render target (u, v, depth or label)"


def render_losses(layers: Sequence[Sequence[torch.Tensor]],
                  render_targets: Sequence[Sequence[torch.Tensor]], cam_from_ego: torch.Tensor,
                  intrinsics: torch.Tensor, image_hw: tuple[int, int],
                  renderer: Callable | None = None, near: float = NEAR_PLANE
                  ) -> tuple[list[RenderLossResult], torch.Tensor]:
    """render_loss of L layers that share the targets and cameras, in one renderer call.

    layers: L tuples (means, scales, rotations, opacities, logits) shaped as in render_loss,
    each with its own number of Gaussians G_l. Every (layer, sample) scene is drawn in one
    call of ``renderer`` (None: ours, render_scenes; else one with its signature), so what a
    call costs the host is paid once per step, not per layer.
    Returns (L RenderLossResults, targets_finite): a 0-dim device bool, false if any target
    holds a NaN or inf (left unread: the caller reads it with its own flags; depth and label
    are not checked otherwise, and make the losses NaN).
    """
    B, N = cam_from_ego.shape[:2]
    if len(render_targets) != B or intrinsics.shape[:2] != (B, N):
        raise ValueError("render_targets / cam_from_ego / intrinsics do not match the batch")
    for means, scales, rotations, opacities, logits in layers:
        G = means.shape[1] if means.ndim == 3 else -1
        if (means.shape != (B, G, 3) or scales.shape != (B, G, 3)
                or rotations.shape != (B, G, 4) or opacities.shape != (B, G)
                or logits.shape[:2] != (B, G)):
            raise ValueError("Gaussian attributes must be [B, G, ...] with the batch's B and "
                             f"one G: means {tuple(means.shape)} scales {tuple(scales.shape)} "
                             f"rotations {tuple(rotations.shape)} opacities "
                             f"{tuple(opacities.shape)} logits {tuple(logits.shape)}")
    device = layers[0][0].device if layers else cam_from_ego.device
    targets = []                                # per sample: N tensors [P_n, 4] on the device
    for b in range(B):
        if len(render_targets[b]) != N:
            raise ValueError(f"sample {b}: {len(render_targets[b])} render target sets for "
                             f"{N} cameras")
        per_camera = [upload(t, device, torch.float32) for t in render_targets[b]]
        if any(t.dim() != 2 or t.shape[1] != 4 for t in per_camera):
            raise ValueError(f"sample {b}: render targets must be [P, 4] (u, v, depth, label)")
        targets.append(per_camera)
    joined = [torch.cat(t) if t else torch.zeros(0, 4, device=device) for t in targets]
    targets_finite = torch.stack([torch.isfinite(t).all() for t in joined]).all() if joined \
        else torch.ones((), dtype=torch.bool, device=device)
    rendered_samples = [b for b in range(B) if joined[b].shape[0]]
    probs = [torch.softmax(logits.float(), dim=-1) for *_, logits in layers]
    scenes = [((means[b].float(), scales[b].float(), rotations[b].float(),
                opacities[b].float(), probs[l][b]), b)
              for l, (means, scales, rotations, opacities, _) in enumerate(layers)
              for b in rendered_samples]
    rendered = []
    if scenes:
        if renderer is None:
            from ..render import render_scenes as renderer
        rendered = renderer(
            [gaussians for gaussians, _ in scenes],
            torch.stack([cam_from_ego[b] for _, b in scenes]).float(),
            torch.stack([intrinsics[b] for _, b in scenes]).float(),
            [[t[:, :2] for t in targets[b]] for _, b in scenes], tuple(image_hw), near=near)
    rendered = iter(rendered)
    num_pixels = sum(joined[b].shape[0] for b in rendered_samples)
    results = []
    for prob in probs:
        num_classes = prob.shape[-1]
        depth_sum = sem_sum = prob.new_zeros(())
        num_labelled = 0
        for b in rendered_samples:
            target = joined[b]
            per_camera = next(rendered)
            depth = torch.cat([r.depth for r in per_camera])
            features = torch.cat([r.features for r in per_camera])
            depth_sum = depth_sum + (depth - target[:, 2]).abs().sum()
            labels = target[:, 3].round().long()
            labelled = (labels >= 0) & (labels < num_classes)
            # every pixel's mass at its (clamped) label, the unlabelled ones weighted 0: the
            # number of labelled pixels stays on the device
            mass = features.gather(1, labels.clamp(0, num_classes - 1)[:, None])[:, 0]
            sem_sum = sem_sum - torch.where(labelled, torch.log(mass + SEMANTIC_EPS), 0).sum()
            num_labelled = num_labelled + labelled.sum()
        results.append(RenderLossResult(
            depth=depth_sum / max(num_pixels, 1),
            semantic=sem_sum / torch.as_tensor(num_labelled).clamp(min=1),
            num_pixels=num_pixels, num_labelled=num_labelled))
    return results, targets_finite


def one_call_per_scene(renderer: Callable) -> Callable:
    """A renderer with the signature of ``render_scenes`` that calls ``renderer`` (with the
    signature of ``render_cameras``) once per scene."""
    def render_each(scenes, cam_from_ego, intrinsics, pixels, image_hw, near=NEAR_PLANE):
        return [renderer(*scene, cam_from_ego[k], intrinsics[k], pixels[k], image_hw, near=near)
                for k, scene in enumerate(scenes)]
    return render_each
