"""The same rendering through gsplat's CUDA rasteriser (``odg train --renderer gsplat``).

``render_scenes_gsplat`` has the signature and results of ``render_scenes`` (and
``render_cameras_gsplat`` those of ``render_cameras``), so the render loss can use either.
All K scenes go to gsplat in one ``rasterization`` call, as its batch: gsplat's host read (the
number of tile intersections, read to size its lists) and the input checks' read are paid
once for every layer and sample of a step. gsplat's batch needs one Gaussian count for all
scenes: smaller scenes are padded with Gaussians of opacity 0, which its projection culls
(no tile, no gradient). gsplat renders every pixel of each camera (fused CUDA kernels, no
Python per pixel), and the requested pixels are read from those images. Where the two
renderers differ:

* gsplat evaluates pixel centres: a requested (u, v) gets the value at the centre of the pixel
  it falls in (floor(u) + 0.5, floor(v) + 0.5), ours the value at (u, v) itself.
* gsplat caps alpha at 0.999, ours at 0.99 (as the original 3D Gaussian splatting does;
  docs/architecture.md sec. 5); below 0.99 they agree.

Everything else is the same convention (projection and its Jacobian clamp, the 0.3 px^2 blur,
the 1/255 skip, the 1e-4 transmittance stop, depth weighted like the features, not
normalised). gsplat's rasteriser has CUDA kernels only: on CPU this raises (the census counts
it through stand-ins of its kernels, ``bench/gsplat_stand_in.py``).
"""
from __future__ import annotations

from typing import Sequence

import torch

from ..transfer import upload
from .projection import BLUR_PX2
from .splat import TILE_SIZE, RenderResult, _raise_failed, scene_inputs


def render_cameras_gsplat(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor,
                          opacities: torch.Tensor, features: torch.Tensor,
                          cam_from_ego: torch.Tensor, intrinsics: torch.Tensor,
                          pixels: Sequence[torch.Tensor], image_hw: Sequence[int],
                          near: float = 0.05, tile_size: int = TILE_SIZE) -> list[RenderResult]:
    """``render_cameras`` (same arguments, same RenderResults) by ``gsplat.rasterization``."""
    return render_scenes_gsplat([(means, scales, rotations, opacities, features)],
                                cam_from_ego[None], intrinsics[None], [pixels], image_hw,
                                near, tile_size)[0]


def render_scenes_gsplat(scenes: Sequence[Sequence[torch.Tensor]], cam_from_ego: torch.Tensor,
                         intrinsics: torch.Tensor, pixels: Sequence[Sequence[torch.Tensor]],
                         image_hw: Sequence[int], near: float = 0.05,
                         tile_size: int = TILE_SIZE) -> list[list[RenderResult]]:
    """``render_scenes`` (same arguments, same RenderResults) by one ``gsplat.rasterization``
    call over the K scenes."""
    if not scenes:
        return []
    (height, width), gaussians, sizes, checks = scene_inputs(
        scenes, cam_from_ego, intrinsics, pixels, image_hw, near, tile_size)
    _raise_failed(checks, torch.stack([flag for _, flag in checks]).tolist())   # one read
    from gsplat import rasterization

    K, N = cam_from_ego.shape[:2]
    means, scales, rotations, opacities, features = padded_scenes(gaussians, sizes)
    with torch.autocast(means.device.type, enabled=False):
        # "RGB+D": the features, then depth composited with the same weights (gsplat "D").
        images, alphas, _ = rasterization(
            means, rotations, scales, opacities, features, cam_from_ego.to(means.dtype),
            intrinsics.to(means.dtype), width, height, near_plane=near, eps2d=BLUR_PX2,
            packed=False, tile_size=int(tile_size), render_mode="RGB+D",
            rasterize_mode="classic")
    # every requested pixel of every camera in one gather from the [K N H W] images
    counts = [int(uv.shape[0]) for per_scene in pixels for uv in per_scene]
    uv = torch.cat([uv.to(means.dtype) for per_scene in pixels for uv in per_scene])
    image = torch.repeat_interleave(torch.arange(K * N, device=means.device),
                                    upload(torch.tensor(counts), means.device),
                                    output_size=sum(counts))
    column = uv[:, 0].floor().long().clamp(0, width - 1)
    row = uv[:, 1].floor().long().clamp(0, height - 1)
    values = images.flatten(0, 1)[image, row, column]        # no copy of the whole images
    alpha = alphas.flatten(0, 1)[image, row, column, 0]
    results = [RenderResult(depth=v[:, -1], features=v[:, :-1], alpha=a)
               for v, a in zip(values.split(counts), alpha.split(counts))]
    return [results[k * N:(k + 1) * N] for k in range(K)]


def padded_scenes(gaussians: Sequence[torch.Tensor], sizes: Sequence[int]):
    """The K scenes' Gaussians (each attribute concatenated over the scenes, ``sizes`` per
    scene) as gsplat's batch [K, G_max, ...]: a scene with fewer Gaussians is padded with
    identity rotations, zero means and scales and opacity 0 (culled by gsplat), gradients
    flowing to the real ones only. Scenes of one size are only reshaped."""
    K, largest = len(sizes), max(sizes)
    if all(size == largest for size in sizes):
        return tuple(t.reshape(K, largest, *t.shape[1:]) for t in gaussians)
    device = gaussians[0].device
    position = upload(torch.cat([torch.arange(size) + k * largest
                                 for k, size in enumerate(sizes)]), device)
    padded = []
    for i, t in enumerate(gaussians):
        base = t.new_zeros(K * largest, *t.shape[1:])
        if i == 2:                                   # rotations (w, x, y, z): the identity
            base[:, 0] = 1.0
        padded.append(base.index_copy(0, position, t).view(K, largest, *t.shape[1:]))
    return tuple(padded)
