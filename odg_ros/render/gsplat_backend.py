"""The same rendering through gsplat's CUDA rasteriser (``odg train --renderer gsplat``).

``render_cameras_gsplat`` has the signature and results of ``render_cameras``, so the render
loss can use either. gsplat renders every pixel of each camera (fused CUDA kernels, no Python
per pixel), and the requested pixels are read from those images. Where the two differ:

* gsplat evaluates pixel centres: a requested (u, v) gets the value at the centre of the pixel
  it falls in (floor(u) + 0.5, floor(v) + 0.5), ours the value at (u, v) itself.
* gsplat caps alpha at 0.999, ours at 0.99 (as the original 3D Gaussian splatting does;
  docs/architecture.md sec. 5); below 0.99 they agree.

Everything else is the same convention (projection and its Jacobian clamp, the 0.3 px^2 blur,
the 1/255 skip, the 1e-4 transmittance stop, depth weighted like the features, not
normalised). gsplat's rasteriser has CUDA kernels only: on CPU this raises.
"""
from __future__ import annotations

from typing import Sequence

import torch

from .projection import BLUR_PX2
from .splat import TILE_SIZE, RenderResult, checked_gaussians


def render_cameras_gsplat(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor,
                          opacities: torch.Tensor, features: torch.Tensor,
                          cam_from_ego: torch.Tensor, intrinsics: torch.Tensor,
                          pixels: Sequence[torch.Tensor], image_hw: Sequence[int],
                          near: float = 0.05, tile_size: int = TILE_SIZE) -> list[RenderResult]:
    """``render_cameras`` (same arguments, same RenderResults) by ``gsplat.rasterization``."""
    (height, width), (means, scales, rotations, opacities, features) = checked_gaussians(
        means, scales, rotations, opacities, features, cam_from_ego, intrinsics, pixels,
        image_hw, near, tile_size)
    from gsplat import rasterization

    with torch.autocast(means.device.type, enabled=False):
        # "RGB+D": the features, then depth composited with the same weights (gsplat "D").
        images, alphas, _ = rasterization(
            means, rotations, scales, opacities, features, cam_from_ego.to(means.dtype),
            intrinsics.to(means.dtype), width, height, near_plane=near, eps2d=BLUR_PX2,
            packed=False, tile_size=int(tile_size), render_mode="RGB+D",
            rasterize_mode="classic")
    results = []
    for camera, uv in enumerate(pixels):
        column = uv[:, 0].floor().long().clamp(0, width - 1)
        row = uv[:, 1].floor().long().clamp(0, height - 1)
        values = images[camera, row, column]
        results.append(RenderResult(depth=values[:, -1], features=values[:, :-1],
                                    alpha=alphas[camera, row, column, 0]))
    return results
