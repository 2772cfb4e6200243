"""Differentiable Gaussian splatting of depth and semantic maps at chosen pixels (paper Eq. 6).

For every requested pixel p of a camera, with the visible Gaussians sorted front to back:

    depth[p]    = sum_i T_i alpha_i d_i        d_i = camera-space z of Gaussian i's mean
    features[p] = sum_i T_i alpha_i c_i        c_i = the Gaussian's feature (class probabilities)
    alpha[p]    = sum_i T_i alpha_i = 1 - T_final        (accumulated opacity)

    alpha_i = min(0.99, o_i exp(-0.5 delta^T Sigma2D_i^-1 delta)),  T_i = prod_{j<i} (1 - alpha_j)

The paper's Eq. 6 writes the depth weight as T_i sigma_i (sigma = opacity); like gsplat's
depth rendering we weight depth with the same T_i alpha_i as the semantics, so depth and
semantics come from one compositing. Depth is not normalised by alpha (gsplat "D", not "ED").

gsplat / Inria numerics: contributions with alpha < 1/255 are skipped, and a pixel stops at
the first Gaussian that would bring its transmittance to <= 1e-4 (that Gaussian is excluded).
Projection conventions: see projection.py.

How it stays fast and bounded without a CUDA kernel: only the requested pixels are evaluated.
Pixels are binned into 16x16 tiles; each splat's alpha >= 1/255 box is intersected with the
tiles, so only (splat, pixel) pairs in touched tiles are ever formed, never a dense
Gaussians x pixels tensor. Candidate pairs are tested without autograd in chunks, the
surviving pairs are sorted by (pixel, depth), and the transmittance is an exclusive segmented
cumulative sum of log(1 - alpha) in float64 (a global cumsum minus its value at each pixel's
first pair; float64 so that subtracting large running sums loses nothing). Memory is
O(surviving pairs); the weighted sum of the features uses a custom autograd function that
does not store the [pairs, C] product.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import torch

from .projection import ALPHA_MAX, ALPHA_MIN, Splats, project_gaussians, splat_power

TRANSMITTANCE_MIN = 1e-4         # a pixel is done once T would reach this (exclusive)
TILE_SIZE = 16                   # pixel tile edge for culling (as gsplat)
CANDIDATE_CHUNK = 4_000_000      # candidate (splat, pixel) pairs tested at once
SUM_CHUNK = 1_000_000            # pairs per step of the weighted feature sum


class RenderResult(NamedTuple):
    """Rendered values at the P requested pixels of one camera.

    depth [P] (metres, = sum T_i alpha_i d_i), features [P, C], alpha [P] (accumulated opacity).
    """

    depth: torch.Tensor
    features: torch.Tensor
    alpha: torch.Tensor


def render_gaussians(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor,
                     opacities: torch.Tensor, features: torch.Tensor,
                     cam_from_ego: torch.Tensor, intrinsics: torch.Tensor, pixels: torch.Tensor,
                     image_hw: Sequence[int], near: float = 0.05,
                     tile_size: int = TILE_SIZE) -> RenderResult:
    """Render depth, features and alpha of one camera at the given pixels.

    means [G, 3] ego frame (m); scales [G, 3] (m); rotations [G, 4] (w, x, y, z), any length
    (shorter than 1e-12 -> identity); opacities [G]; features [G, C];
    cam_from_ego [4, 4] rigid; intrinsics [3, 3] (of the image the pixels refer to, no skew);
    pixels [P, 2] (u, v) in pixels, pixel centres at +0.5, inside [0, W] x [0, H];
    image_hw (H, W). Differentiable w.r.t. means, scales, rotations, opacities and features.
    Returns RenderResult(depth [P], features [P, C], alpha [P]).
    """
    if cam_from_ego.shape != (4, 4) or intrinsics.shape != (3, 3):
        raise ValueError(f"cam_from_ego must be [4, 4] and intrinsics [3, 3], got "
                         f"{tuple(cam_from_ego.shape)} and {tuple(intrinsics.shape)}")
    return render_cameras(means, scales, rotations, opacities, features, cam_from_ego[None],
                          intrinsics[None], [pixels], image_hw, near=near, tile_size=tile_size)[0]


def render_cameras(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor,
                   opacities: torch.Tensor, features: torch.Tensor,
                   cam_from_ego: torch.Tensor, intrinsics: torch.Tensor,
                   pixels: Sequence[torch.Tensor], image_hw: Sequence[int], near: float = 0.05,
                   tile_size: int = TILE_SIZE) -> list[RenderResult]:
    """Render the same Gaussians into N cameras of one size at once (one pass, one sort).

    Gaussian tensors as in render_gaussians; cam_from_ego [N, 4, 4]; intrinsics [N, 3, 3];
    pixels: N tensors [P_n, 2]; image_hw (H, W) shared. Returns N RenderResults.
    """
    height, width = _check_inputs(means, scales, rotations, opacities, features, cam_from_ego,
                                  intrinsics, pixels, image_hw, near, tile_size)
    num_cameras = cam_from_ego.shape[0]
    counts = [int(p.shape[0]) for p in pixels]
    pixel_uv = torch.cat([p.to(means.dtype) for p in pixels], dim=0) if pixels else \
        means.new_zeros(0, 2)
    pixel_camera = torch.repeat_interleave(
        torch.arange(num_cameras, device=means.device),
        torch.tensor(counts, device=means.device, dtype=torch.long))

    splats = project_gaussians(means, scales, rotations, opacities, cam_from_ego.to(means.dtype),
                               intrinsics.to(means.dtype), (height, width), near)
    pair_splat, pair_pixel = _contributing_pairs(splats, pixel_uv, pixel_camera, num_cameras,
                                                 (height, width), tile_size)
    weights = _compositing_weights(splats, pixel_uv, pair_splat, pair_pixel, pixel_uv.shape[0])

    # One weighted sum gives features, depth and accumulated alpha (a column of ones).
    values = torch.cat([features[splats.gaussian], splats.depth[:, None],
                        torch.ones_like(splats.depth)[:, None]], dim=-1)      # [S, C + 2]
    rendered = _PairWeightedSum.apply(weights, values, pair_pixel, pair_splat,
                                      pixel_uv.shape[0])                     # [P, C + 2]
    results = []
    for chunk in rendered.split(counts, dim=0):
        results.append(RenderResult(depth=chunk[:, -2], features=chunk[:, :-2],
                                    alpha=chunk[:, -1]))
    return results


def _contributing_pairs(splats: Splats, pixel_uv: torch.Tensor, pixel_camera: torch.Tensor,
                        num_cameras: int, image_hw, tile_size: int):
    """(splat, pixel) pairs with alpha >= 1/255, sorted by pixel then depth. -> 2 x [M] long.

    Splat -> tiles its alpha box touches -> the requested pixels in those tiles; each
    candidate is then tested exactly, without autograd, CANDIDATE_CHUNK pairs at a time.
    """
    device = pixel_uv.device
    height, width = image_hw
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    tiles_per_camera = tiles_x * tiles_y
    num_splats = len(splats)
    empty = torch.zeros(0, dtype=torch.long, device=device)
    if num_splats == 0 or pixel_uv.shape[0] == 0:
        return empty, empty

    with torch.no_grad():
        # Pixels grouped by tile (a monotone clamped floor, so pixel-in-box implies
        # tile-in-tile-range for the boxes below).
        pixel_tile = (pixel_camera * tiles_per_camera
                      + _tile_index(pixel_uv[:, 1], tile_size, tiles_y) * tiles_x
                      + _tile_index(pixel_uv[:, 0], tile_size, tiles_x))
        pixels_by_tile = torch.argsort(pixel_tile, stable=True)
        tile_pixel_count = torch.bincount(pixel_tile, minlength=num_cameras * tiles_per_camera)
        tile_first_pixel = torch.cumsum(tile_pixel_count, 0) - tile_pixel_count

        # Splat -> touched tiles.
        lo = splats.mean2d.detach() - splats.half_extent
        hi = splats.mean2d.detach() + splats.half_extent
        tx0, tx1 = _tile_index(lo[:, 0], tile_size, tiles_x), _tile_index(hi[:, 0], tile_size, tiles_x)
        ty0, ty1 = _tile_index(lo[:, 1], tile_size, tiles_y), _tile_index(hi[:, 1], tile_size, tiles_y)
        span_x = tx1 - tx0 + 1
        tiles_of_splat = span_x * (ty1 - ty0 + 1)
        st_splat = torch.repeat_interleave(torch.arange(num_splats, device=device), tiles_of_splat)
        st_local = torch.arange(st_splat.shape[0], device=device) - torch.repeat_interleave(
            torch.cumsum(tiles_of_splat, 0) - tiles_of_splat, tiles_of_splat)
        st_tile = (splats.camera[st_splat] * tiles_per_camera
                   + (ty0[st_splat] + st_local // span_x[st_splat]) * tiles_x
                   + tx0[st_splat] + st_local % span_x[st_splat])
        st_count = tile_pixel_count[st_tile]
        occupied = st_count > 0
        st_splat, st_tile, st_count = st_splat[occupied], st_tile[occupied], st_count[occupied]

        # Expand (splat, tile) -> (splat, pixel) in chunks of ~CANDIDATE_CHUNK candidates.
        mean2d = splats.mean2d.detach()
        cov_xy, cov_yy, det = splats.cov_xy.detach(), splats.cov_yy.detach(), splats.det.detach()
        opacity = splats.opacity.detach()
        kept_splat, kept_pixel = [], []
        ends = torch.cumsum(st_count, 0)
        start = 0
        while start < st_count.shape[0]:
            budget_end = (ends[start - 1] if start > 0 else 0) + CANDIDATE_CHUNK
            stop = max(start + 1, int(torch.searchsorted(ends, budget_end, right=True)))
            count = st_count[start:stop]
            cand_splat = torch.repeat_interleave(st_splat[start:stop], count)
            offset_in_tile = torch.arange(cand_splat.shape[0], device=device) - \
                torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
            cand_pixel = pixels_by_tile[
                torch.repeat_interleave(tile_first_pixel[st_tile[start:stop]], count) + offset_in_tile]
            alpha = _pair_alpha(mean2d, cov_xy, cov_yy, det, opacity, pixel_uv,
                                cand_splat, cand_pixel)
            contributes = alpha >= ALPHA_MIN
            kept_splat.append(cand_splat[contributes])
            kept_pixel.append(cand_pixel[contributes])
            start = stop
        if not kept_splat:
            return empty, empty
        pair_splat = torch.cat(kept_splat)
        pair_pixel = torch.cat(kept_pixel)
        # Splats are depth-sorted, so the splat index is the depth rank.
        order = torch.argsort(pair_pixel * num_splats + pair_splat)
    return pair_splat[order], pair_pixel[order]


def _tile_index(coordinate: torch.Tensor, tile_size: int, num_tiles: int) -> torch.Tensor:
    return torch.floor(coordinate / tile_size).clamp(0, num_tiles - 1).long()


def _pair_alpha(mean2d, cov_xy, cov_yy, det, opacity, pixel_uv, pair_splat, pair_pixel):
    """alpha = min(0.99, o exp(-power)) of each (splat, pixel) pair. -> [M]."""
    delta = pixel_uv[pair_pixel] - mean2d[pair_splat]
    power = splat_power(cov_xy[pair_splat], cov_yy[pair_splat], det[pair_splat],
                        delta[:, 0], delta[:, 1])
    return (opacity[pair_splat] * torch.exp(-power)).clamp_max(ALPHA_MAX)


def _compositing_weights(splats: Splats, pixel_uv: torch.Tensor, pair_splat: torch.Tensor,
                         pair_pixel: torch.Tensor, num_pixels: int) -> torch.Tensor:
    """w = T alpha of each pair (pairs sorted by pixel, then front to back). -> [M].

    T is exp of the exclusive per-pixel cumsum of log(1 - alpha), in float64. A pair is kept
    while T (1 - alpha) > 1e-4; since T only decreases along a pixel, the kept pairs are a
    prefix, exactly as in the sequential early stop.
    """
    alpha = _pair_alpha(splats.mean2d, splats.cov_xy, splats.cov_yy, splats.det,
                        splats.opacity, pixel_uv, pair_splat, pair_pixel)
    if pair_splat.shape[0] == 0:
        return alpha
    contributes = alpha.detach() >= ALPHA_MIN
    log_keep = torch.where(contributes, torch.log1p(-alpha.double()), 0.0)   # log(1 - alpha)
    running = torch.cumsum(log_keep, 0) - log_keep                            # exclusive
    pairs_per_pixel = torch.bincount(pair_pixel, minlength=num_pixels)
    first_pair = torch.cumsum(pairs_per_pixel, 0) - pairs_per_pixel
    log_transmittance = running - running[first_pair[pair_pixel]]
    with torch.no_grad():
        before_stop = (log_transmittance + log_keep) > math.log(TRANSMITTANCE_MIN)
    include = contributes & before_stop
    weight = alpha * torch.exp(log_transmittance).to(alpha.dtype)
    return torch.where(include, weight, torch.zeros_like(weight))


class _PairWeightedSum(torch.autograd.Function):
    """out[p] = sum over pairs m with pixel[m] = p of weight[m] * values[splat[m]].

    weight [M], values [S, D], pixel [M], splat [M] long, num_pixels -> out [P, D].
    Chunked so no [M, D] tensor is kept for backward (autograd would store one).
    """

    @staticmethod
    def forward(ctx, weight, values, pixel, splat, num_pixels):
        out = values.new_zeros(num_pixels, values.shape[1])
        for lo in range(0, weight.shape[0], SUM_CHUNK):
            hi = lo + SUM_CHUNK
            out.index_add_(0, pixel[lo:hi], weight[lo:hi, None] * values[splat[lo:hi]])
        ctx.save_for_backward(weight, values, pixel, splat)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        weight, values, pixel, splat = ctx.saved_tensors
        grad_weight = grad_values = None
        if ctx.needs_input_grad[0]:
            grad_weight = torch.empty_like(weight)
            for lo in range(0, weight.shape[0], SUM_CHUNK):
                hi = lo + SUM_CHUNK
                grad_weight[lo:hi] = (grad_out[pixel[lo:hi]] * values[splat[lo:hi]]).sum(-1)
        if ctx.needs_input_grad[1]:
            grad_values = torch.zeros_like(values)
            for lo in range(0, weight.shape[0], SUM_CHUNK):
                hi = lo + SUM_CHUNK
                grad_values.index_add_(0, splat[lo:hi], weight[lo:hi, None] * grad_out[pixel[lo:hi]])
        return grad_weight, grad_values, None, None, None


def _check_inputs(means, scales, rotations, opacities, features, cam_from_ego, intrinsics,
                  pixels, image_hw, near, tile_size) -> tuple[int, int]:
    """Clear errors for malformed input; returns (H, W)."""
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [G, 3], got {tuple(means.shape)}")
    g = means.shape[0]
    expected = {"scales": (scales, (g, 3)), "rotations": (rotations, (g, 4)),
                "opacities": (opacities, (g,))}
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"{name} must be {list(shape)}, got {tuple(tensor.shape)}")
    if features.ndim != 2 or features.shape[0] != g:
        raise ValueError(f"features must be [G={g}, C], got {tuple(features.shape)}")
    if not means.dtype.is_floating_point:
        raise ValueError(f"means must be floating point, got {means.dtype}")
    named = {"means": means, "scales": scales, "rotations": rotations, "opacities": opacities,
             "features": features}
    for name, tensor in named.items():
        if tensor.dtype != means.dtype or tensor.device != means.device:
            raise ValueError(f"{name} is {tensor.dtype} on {tensor.device}; expected "
                             f"{means.dtype} on {means.device} like means")
    if cam_from_ego.ndim != 3 or cam_from_ego.shape[1:] != (4, 4):
        raise ValueError(f"cam_from_ego must be [N, 4, 4], got {tuple(cam_from_ego.shape)}")
    n = cam_from_ego.shape[0]
    if tuple(intrinsics.shape) != (n, 3, 3):
        raise ValueError(f"intrinsics must be [N={n}, 3, 3], got {tuple(intrinsics.shape)}")
    if len(pixels) != n:
        raise ValueError(f"got {len(pixels)} pixel sets for {n} cameras")
    if len(image_hw) != 2 or int(image_hw[0]) <= 0 or int(image_hw[1]) <= 0:
        raise ValueError(f"image_hw must be (H, W) > 0, got {image_hw}")
    height, width = int(image_hw[0]), int(image_hw[1])
    if not (math.isfinite(near) and near > 0):
        raise ValueError(f"near must be a positive number, got {near}")
    if int(tile_size) <= 0:
        raise ValueError(f"tile_size must be positive, got {tile_size}")
    named.update(cam_from_ego=cam_from_ego, intrinsics=intrinsics)
    for name, tensor in named.items():
        if not torch.isfinite(tensor).all():
            raise ValueError(f"{name} contains NaN or inf")
    rot = cam_from_ego[:, :3, :3].double()
    eye = torch.eye(3, dtype=torch.float64, device=rot.device)
    if ((rot @ rot.transpose(1, 2) - eye).abs().gt(1e-3).any()
            or (torch.linalg.det(rot) - 1).abs().gt(1e-3).any()):
        raise ValueError("cam_from_ego must be rigid (orthonormal rotation, det +1)")
    k = intrinsics.double()
    if (k[:, 0, 0] <= 0).any() or (k[:, 1, 1] <= 0).any():
        raise ValueError("intrinsics must have positive focal lengths")
    if (k[:, 0, 1].abs() > 1e-6 * k[:, 0, 0]).any():
        raise ValueError("intrinsics with skew are not supported")
    for i, p in enumerate(pixels):
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"pixels[{i}] must be [P, 2] (u, v), got {tuple(p.shape)}")
        if p.device != means.device:
            raise ValueError(f"pixels[{i}] is on {p.device}, Gaussians on {means.device}")
        if p.shape[0] and not (torch.isfinite(p).all() and (p[:, 0] >= 0).all()
                               and (p[:, 0] <= width).all() and (p[:, 1] >= 0).all()
                               and (p[:, 1] <= height).all()):
            raise ValueError(f"pixels[{i}] must be finite and inside [0, W={width}] x "
                             f"[0, H={height}]")
    return height, width
