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

How it stays fast and bounded without a CUDA kernel (details in _composite): only the
requested pixels are evaluated. Pixels are binned into 16x16 tiles and each splat is paired
only with the tiles its alpha >= 1/255 box touches, so only (splat, pixel) pairs in touched
tiles are ever formed, never a dense Gaussians x pixels tensor. Splats go front to back: a
first depth batch of the front quarter of the candidate pairs (at least ~1M), then the rest,
of the pixels still active, in chunks as large as a share of the device's memory allows
(later_batch_candidates: one at training sizes). Candidates are tested without autograd,
survivors get T from a float64 segmented cumulative sum of log(1 - alpha), and pixels that
reached the early stop leave the rest (in a dense scene the first batch stops most of them).
The weighted sums are CSR sparse x dense products. The host waits for the device once for
every size and input check before compositing (visible splats, tile pairs, and the first
depth batch's bounds from a summed-area table of pixels per tile, in one copy) and once
after the first batch (the count of its kept pairs with the rest's size); the projection
(every camera x Gaussian pair, the others marked invisible) and the rest's chunks (stopped
pixels and dropped pairs masked, not removed) wait for nothing. So a render call waits
twice, whatever the scene, the image and the batch.
Memory is O(the first batch's contributing pairs and the rest's candidates) plus one
chunk's working memory. render_scenes draws several
independent scenes (the render loss: every decoder layer of every sample) in one such pass, so
those reads are paid once for all of them.

The code is device-agnostic PyTorch but has only been run on CPU; on CUDA, gsplat_backend.py
renders the same with gsplat's rasteriser. test/render/test_render_gsplat.py checks this renderer
against gsplat's own pure-PyTorch projection composited with its CUDA kernel's rules, at every
pixel. The one difference is deliberate: gsplat caps alpha at 0.999, we cap it at 0.99
(ALPHA_MAX) as the original 3D Gaussian splatting does.
"""
from __future__ import annotations

import math
import os
import warnings
from typing import NamedTuple, Sequence

import torch

from ..transfer import upload
from .projection import (ALPHA_MAX, ALPHA_MIN, Splats, depth_order, project_candidates,
                         splat_power)

TRANSMITTANCE_MIN = 1e-4         # a pixel is done once T would reach this (exclusive)
# Two splats at the alpha cap leave T = (1 - 0.99)^2 = 1e-4, exactly the cut, a common case
# (opacity saturates). T is compared in log space after a segmented cumsum whose rounding
# (~1e-9 over a million pairs) would decide that tie differently from pixel to pixel; this
# margin resolves it, and anything within a relative 1e-7 of the cut, as exact arithmetic
# and gsplat do (T <= 1e-4: stop).
STOP_LOG_MARGIN = 1e-7
TILE_SIZE = 16                   # pixel tile edge for culling (as gsplat)
# The first depth batch: the front FIRST_BATCH_SHARE of all candidate (splat, pixel) pairs,
# at least CANDIDATE_CHUNK of them. It stops most pixels of a dense scene early; the rest, of
# the pixels still active, is sized in the one read after it and drawn in chunks as large as
# the device's memory allows (later_batch_candidates), which read nothing: the host's waits
# do not grow with the image or the batch.
CANDIDATE_CHUNK = 1_000_000
FIRST_BATCH_SHARE = 0.25
LATER_CANDIDATE_CHUNK = None     # candidates per chunk of the rest; None: from the memory
BATCH_MEMORY_SHARE = 0.1         # of the device's memory a chunk may use
BYTES_PER_CANDIDATE = 200        # a batch's working memory per candidate pair, at most
CHECK_CSR = False                # the CSR matrices are valid by construction (a test checks)


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
                   tile_size: int = TILE_SIZE,
                   wait_free: bool | None = None) -> list[RenderResult]:
    """Render the same Gaussians into N cameras of one size at once (one pass, one sort).

    Gaussian tensors as in render_gaussians; cam_from_ego [N, 4, 4]; intrinsics [N, 3, 3];
    pixels: N tensors [P_n, 2]; image_hw (H, W) shared. Returns N RenderResults.
    Always computed in float32 or float64, whatever autocast is active: half-precision
    Gaussians are rendered (and returned) in float32. Projection to pixels needs more than
    bf16's 8 mantissa bits (a 704 px image has a 4 px step there) and the sparse products
    have no half-precision CPU kernels.
    wait_free: draw what follows the first depth batch without reading the device (its
    dropped pairs masked, not removed); None: off the CPU only. On the CPU a read costs
    nothing and removing the dropped pairs saves time, so each chunk is compacted there.
    """
    (height, width), (means, scales, rotations, opacities, features), checks = \
        _gaussians_and_checks(means, scales, rotations, opacities, features, cam_from_ego,
                              intrinsics, pixels, image_hw, near, tile_size)
    with torch.autocast(means.device.type, enabled=False):
        return _render_scenes(means, scales, rotations, opacities, features, None, None,
                              cam_from_ego, intrinsics, pixels, height, width, near, tile_size,
                              checks, wait_free)


def render_scenes(scenes: Sequence[Sequence[torch.Tensor]], cam_from_ego: torch.Tensor,
                  intrinsics: torch.Tensor, pixels: Sequence[Sequence[torch.Tensor]],
                  image_hw: Sequence[int], near: float = 0.05, tile_size: int = TILE_SIZE,
                  wait_free: bool | None = None) -> list[list[RenderResult]]:
    """render_cameras of K independent scenes in one pass: what one call costs the host (its
    reads of sizes from the device) is paid once for all K.

    scenes: K tuples (means, scales, rotations, opacities, features) as in render_cameras,
    each with its own number of Gaussians and one dtype and device for all; cam_from_ego
    [K, N, 4, 4], intrinsics [K, N, 3, 3]: scene k seen by its own N cameras; pixels: K lists
    of N tensors [P, 2]; wait_free as in render_cameras. Returns K lists of N RenderResults, each equal to render_cameras of
    that scene alone (to float64 rounding of the transmittance sums).
    """
    if not scenes:
        _check_scenes(scenes, cam_from_ego, intrinsics, pixels)
        return []
    (height, width), (means, scales, rotations, opacities, features), sizes, checks = \
        scene_inputs(scenes, cam_from_ego, intrinsics, pixels, image_hw, near, tile_size)
    num_cameras = cam_from_ego.shape[1]
    gaussian_scene = torch.repeat_interleave(
        torch.arange(len(scenes), device=means.device),
        upload(torch.tensor(sizes), means.device), output_size=means.shape[0])
    flat_pixels = [p for per_scene in pixels for p in per_scene]
    with torch.autocast(means.device.type, enabled=False):
        results = _render_scenes(means, scales, rotations, opacities, features, gaussian_scene,
                                 num_cameras, cam_from_ego.flatten(0, 1), intrinsics.flatten(0, 1),
                                 flat_pixels, height, width, near, tile_size, checks,
                                 wait_free)
    return [results[k * num_cameras:(k + 1) * num_cameras] for k in range(len(scenes))]


def scene_inputs(scenes, cam_from_ego, intrinsics, pixels, image_hw, near, tile_size):
    """What render_scenes and gsplat's do first: clear errors for malformed shapes, every
    scene's Gaussians concatenated (in float32 if half) and the value checks of all of them,
    unread (as in _check_inputs). Returns ((H, W), (means, scales, rotations, opacities,
    features) of all scenes, the scenes' Gaussian counts, checks)."""
    _check_scenes(scenes, cam_from_ego, intrinsics, pixels)
    # every value check below covers all scenes in one read
    gaussians = [torch.cat([scene[i] for scene in scenes]) for i in range(5)]
    flat_pixels = [p for per_scene in pixels for p in per_scene]
    hw, gaussians, checks = _gaussians_and_checks(
        *gaussians, cam_from_ego.flatten(0, 1), intrinsics.flatten(0, 1), flat_pixels,
        image_hw, near, tile_size)
    return hw, gaussians, [int(scene[0].shape[0]) for scene in scenes], checks


def _check_scenes(scenes, cam_from_ego, intrinsics, pixels) -> None:
    if cam_from_ego.ndim != 4 or intrinsics.ndim != 4 or len(scenes) != cam_from_ego.shape[0]:
        raise ValueError(f"{len(scenes)} scenes need cam_from_ego [K={len(scenes)}, N, 4, 4] "
                         f"and intrinsics [K, N, 3, 3], got {tuple(cam_from_ego.shape)} and "
                         f"{tuple(intrinsics.shape)}")
    if len(pixels) != len(scenes):
        raise ValueError(f"got {len(pixels)} pixel lists for {len(scenes)} scenes")
    for k, scene in enumerate(scenes):
        if len(scene) != 5:
            raise ValueError(f"scene {k} must be (means, scales, rotations, opacities, "
                             f"features), got {len(scene)} tensors")
        _check_shapes(*scene)
        first = scenes[0]
        if (scene[0].dtype, scene[0].device, scene[4].shape[1]) != \
                (first[0].dtype, first[0].device, first[4].shape[1]):
            raise ValueError(f"scene {k} is {scene[0].dtype} on {scene[0].device} with "
                             f"{scene[4].shape[1]} features; scene 0 is {first[0].dtype} on "
                             f"{first[0].device} with {first[4].shape[1]}")


def _gaussians_and_checks(means, scales, rotations, opacities, features, cam_from_ego,
                          intrinsics, pixels, image_hw, near, tile_size):
    """Clear errors for malformed input and half-precision Gaussians in float32, with the
    value checks returned unread (as in _check_inputs)."""
    height, width, checks = _check_inputs(means, scales, rotations, opacities, features,
                                          cam_from_ego, intrinsics, pixels, image_hw, near,
                                          tile_size)
    gaussians = (means, scales, rotations, opacities, features)
    if means.dtype in (torch.float16, torch.bfloat16):
        gaussians = tuple(t.float() for t in gaussians)
    return (height, width), gaussians, checks


def _render_scenes(means, scales, rotations, opacities, features, gaussian_scene,
                   cameras_per_scene, cam_from_ego, intrinsics, pixels, height, width, near,
                   tile_size, checks, wait_free) -> list[RenderResult]:
    """Inputs of one float32/float64 dtype, autocast off, shapes checked; checks: the value
    checks, unread (_check_inputs). gaussian_scene [G] (None: one scene) picks the cameras a
    Gaussian is seen by: the cameras_per_scene of its scene in cam_from_ego [K N, 4, 4]
    (scene-major). Returns K N RenderResults."""
    num_cameras = cam_from_ego.shape[0]
    counts = [int(p.shape[0]) for p in pixels]
    pixel_uv = torch.cat([p.to(means.dtype) for p in pixels], dim=0) if pixels else \
        means.new_zeros(0, 2)
    pixel_camera = torch.repeat_interleave(
        torch.arange(num_cameras, device=means.device),
        upload(torch.tensor(counts, dtype=torch.long), means.device), output_size=sum(counts))

    candidates, visible = project_candidates(
        means, scales, rotations, opacities, cam_from_ego.to(means.dtype),
        intrinsics.to(means.dtype), (height, width), near, gaussian_scene=gaussian_scene,
        cameras_per_scene=cameras_per_scene)
    grid = _TileGrid(height, width, tile_size, num_cameras)
    binned = grid.bin_pixels(pixel_uv, pixel_camera,
                             torch.ones(pixel_uv.shape[0], dtype=torch.bool,
                                        device=means.device))
    keep, boxes, num_tile_pairs, first_batch = _visible_splats(candidates, visible, grid,
                                                               binned[1], checks)
    splats = candidates.take(keep)
    weights, pair_pixel, pair_splat = _composite(splats, pixel_uv, pixel_camera, grid, binned,
                                                 boxes, num_tile_pairs, first_batch, wait_free)

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


@torch.no_grad()
def _visible_splats(candidates: Splats, visible: torch.Tensor, grid: "_TileGrid",
                    tile_count: torch.Tensor, checks):
    """The one host read before compositing: the number of visible splats, of their (splat,
    tile) pairs and the first depth batch's bounds, with the projection's overflow flag and
    the input checks (raised here, before any size is used).

    tile_count [num_tiles]: requested pixels per tile. Returns (the candidates to keep: the
    visible splats sorted by depth, as project_gaussians gives them; their boxes of tiles
    (row0, row1, col0, col1) [S] long; the number of their (splat, tile) pairs; the first
    depth batch as (first pair past it, first splat past it, its candidate pairs)).
    """
    order = depth_order(candidates, visible)
    lo = candidates.mean2d - candidates.half_extent
    hi = candidates.mean2d + candidates.half_extent
    # invisible or overflowing splats touch no tile (their indices would be garbage)
    boxed = visible & torch.isfinite(lo).all(-1) & torch.isfinite(hi).all(-1)
    col0, col1 = (torch.where(boxed, grid.column(x), 0) for x in (lo[:, 0], hi[:, 0]))
    row0, row1 = (torch.where(boxed, grid.row(y), 0) for y in (lo[:, 1], hi[:, 1]))
    tiles_of_splat = torch.where(boxed, (col1 - col0 + 1) * (row1 - row0 + 1), 0)[order]
    pairs_of_splat = torch.where(boxed, _pixels_in_boxes(
        grid, tile_count, candidates.camera, row0, row1, col0, col1), 0)[order]
    zero = pairs_of_splat.new_zeros(1)
    pairs_before = torch.cat([zero, torch.cumsum(pairs_of_splat, 0)])      # before splat i
    tiles_before = torch.cat([zero, torch.cumsum(tiles_of_splat, 0)])
    num_visible = visible.sum()
    # whole splats up to a share of all candidates (at least CANDIDATE_CHUNK), at least one:
    # the same front share of every scene whatever their number
    first_batch = torch.clamp_min((pairs_before[-1:] * FIRST_BATCH_SHARE).long(),
                                  CANDIDATE_CHUNK)
    last = torch.minimum(torch.searchsorted(pairs_before[1:], first_batch,
                                            right=True).clamp_min(1), num_visible)
    read = torch.cat([num_visible[None], tiles_before[-1:], candidates.overflow[None], last,
                      tiles_before.index_select(0, last), pairs_before.index_select(0, last)]
                     + [flag[None] for _, flag in checks]).tolist()
    num_visible, num_tile_pairs, overflow, last, tile_pairs_before, num_candidates = read[:6]
    _raise_failed(checks, read[6:])
    if overflow:
        raise FloatingPointError("Gaussian projection overflowed (non-finite 2D mean or "
                                 "covariance); scales or positions are out of range")
    keep = order[:num_visible]
    boxes = tuple(edge[keep] for edge in (row0, row1, col0, col1))
    return keep, boxes, num_tile_pairs, (tile_pairs_before, last, num_candidates)


def _pixels_in_boxes(grid: "_TileGrid", tile_count: torch.Tensor, camera: torch.Tensor,
                     row0: torch.Tensor, row1: torch.Tensor, col0: torch.Tensor,
                     col1: torch.Tensor) -> torch.Tensor:
    """Binned pixels in each box of tiles [row0, row1] x [col0, col1] of a camera (the
    candidate pairs of a splat), from a summed-area table: no (splat, tile) list needed."""
    table = tile_count.new_zeros(grid.num_cameras, grid.tiles_y + 1, grid.tiles_x + 1)
    table[:, 1:, 1:] = tile_count.view(grid.num_cameras, grid.tiles_y,
                                       grid.tiles_x).cumsum(1).cumsum(2)
    table = table.flatten()

    def corner(row, col):
        return table[(camera * (grid.tiles_y + 1) + row) * (grid.tiles_x + 1) + col]

    return (corner(row1 + 1, col1 + 1) - corner(row0, col1 + 1) - corner(row1 + 1, col0)
            + corner(row0, col0))


def _composite(splats: Splats, pixel_uv: torch.Tensor, pixel_camera: torch.Tensor,
               grid: "_TileGrid", binned, boxes, num_tile_pairs: int, first_batch,
               wait_free: bool | None = None):
    """Compositing weights w = T alpha of every contributing (splat, pixel) pair.

    binned: grid.bin_pixels of every pixel; boxes, num_tile_pairs and first_batch: from
    _visible_splats. Returns weight [M] (differentiable; 0 for pairs masked, not removed),
    pixel [M], splat [M] (long).

    Splats are processed front to back: a first depth batch of whole splats (a quarter of
    the candidate pairs, at least CANDIDATE_CHUNK), then the rest in chunks of at most
    later_batch_candidates pairs. Within each: splat -> tiles its alpha box touches -> the
    requested pixels binned in those tiles -> pairs sorted by (pixel, depth) -> without
    autograd, the exact alpha test and T from the pixel's running log transmittance plus an
    exclusive segmented cumsum of log(1 - alpha), in float64 (a global cumsum minus its value
    at each pixel's first pair; float64 so the subtraction of large running sums loses
    nothing; pairs below alpha 1/255 add 0). A pair is kept while it contributes and
    T (1 - alpha) > 1e-4; T only decreases, so the kept pairs are a prefix of the
    contributing ones as in the sequential early stop. The first batch's kept pairs are
    compacted (their count read with the rest's size: the one wait here), and the pixels that
    stopped leave the rest (this is what keeps dense scenes cheap). The rest's chunks are
    positions in one list of its candidate pairs, so their shapes are known without a read;
    pixels stopping within the rest and pairs not kept are masked (weight 0, log T
    unchanged). Unless ``wait_free`` (None: off the CPU), each chunk's kept pairs are
    compacted instead, with a read of their count. T is then computed again, differentiably,
    from the kept pairs alone. Long because the first batch and the chunks share the running
    log T and the pair lists (one closure), and the order of their waits is the point.
    """
    device = pixel_uv.device
    num_pixels = pixel_uv.shape[0]
    params = torch.stack([splats.mean2d[:, 0], splats.mean2d[:, 1], splats.cov_xy,
                          splats.cov_yy, splats.det, splats.opacity], dim=-1)    # [S, 6]
    weights, pair_pixels, pair_splats = [], [], []
    log_t = torch.zeros(num_pixels, dtype=torch.float64, device=device)      # running log T

    def composite(pair_splat, pair_pixel, kept):
        """Differentiable weights of the batch's pairs (kept: which of them count; None:
        all), appended; the running log T advanced. The kept pairs of a pixel are a prefix
        of its contributing pairs, so T from the kept pairs alone is the same T."""
        nonlocal log_t
        alpha = _pair_alpha(params, pixel_uv, pair_splat, pair_pixel)
        log_one_minus = torch.log1p(-alpha.double())
        if kept is not None:
            log_one_minus = torch.where(kept, log_one_minus, 0.0)
        weight = alpha * torch.exp(
            _log_transmittance(log_one_minus, pair_pixel, log_t)).to(alpha.dtype)
        weights.append(weight if kept is None else torch.where(kept, weight, 0.0))
        pair_pixels.append(pair_pixel)
        pair_splats.append(pair_splat)
        log_t = log_t.index_add(0, pair_pixel, log_one_minus)

    if len(splats) and num_pixels:
        st_splat, st_tile = _splat_tiles(splats, grid, boxes, num_tile_pairs)
        tile_pairs_first, last, num_candidates = first_batch
        stopped = torch.zeros(num_pixels, dtype=torch.bool, device=device)
        with torch.no_grad():
            pair_splat, pair_pixel, kept, stopped = _pairs_of_batch(
                params, pixel_uv, st_splat[:tile_pairs_first], st_tile[:tile_pairs_first],
                binned, (0, num_candidates), log_t, stopped)
        with torch.no_grad():
            # Pixels that stopped leave the rest, whose size comes in the same read as this
            # batch's kept count: the one wait here, also where the rest is empty (so that
            # a call waits the same whatever the scene).
            binned = grid.bin_pixels(pixel_uv, pixel_camera, ~stopped)
            rest = _pixels_in_boxes(grid, binned[1], splats.camera[last:],
                                    *(edge[last:] for edge in boxes)).sum()
            num_kept, rest = torch.stack([kept.sum(), rest]).tolist()
            kept = _compacted(kept, num_kept)
            pair_splat, pair_pixel = (x.index_select(0, kept) for x in (pair_splat, pair_pixel))
        composite(pair_splat, pair_pixel, None)
        # The rest in chunks of at most later_batch_candidates pairs, front to back, the same
        # pixel lists throughout: pixels stopping meanwhile are masked, not re-binned, and
        # pairs not kept masked, not compacted, so that no chunk waits for the device.
        chunk = later_batch_candidates(device)
        for start in range(0, rest, chunk):
            with torch.no_grad():
                pair_splat, pair_pixel, kept, stopped = _pairs_of_batch(
                    params, pixel_uv, st_splat[tile_pairs_first:], st_tile[tile_pairs_first:],
                    binned, (start, min(start + chunk, rest)), log_t, stopped)
                if not (device.type != "cpu" if wait_free is None else wait_free):
                    kept = _compacted(kept, int(kept.sum()))
                    pair_splat, pair_pixel = (x.index_select(0, kept)
                                              for x in (pair_splat, pair_pixel))
                    kept = None
            composite(pair_splat, pair_pixel, kept)
    if not weights:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return params[:0, 0] * 0, empty, empty
    return torch.cat(weights), torch.cat(pair_pixels), torch.cat(pair_splats)


def _pairs_of_batch(params: torch.Tensor, pixel_uv: torch.Tensor, st_splat: torch.Tensor,
                    st_tile: torch.Tensor, binned, positions, log_t: torch.Tensor,
                    stopped: torch.Tensor):
    """A depth batch, without autograd: the candidate (splat, pixel) pairs at ``positions``
    (start, stop) of the (splat, tile) pairs' binned pixels, sorted by (pixel, depth), the
    exact alpha test and the early stop (pixels already ``stopped`` take no part) -> the
    pairs' splat and pixel, which of them are kept, and the pixels stopped after it."""
    pixels_by_tile, tile_count, tile_first = binned
    pair_splat, pair_pixel = _candidate_pairs(st_splat, st_tile, pixels_by_tile, tile_count,
                                              tile_first, *positions)
    # By pixel, then depth: the candidates come in splat order, which is the depth order, so
    # a stable sort by pixel keeps it within each pixel.
    order = torch.argsort(pair_pixel, stable=True)
    pair_splat, pair_pixel = pair_splat[order], pair_pixel[order]
    alpha = _pair_alpha(params.detach(), pixel_uv, pair_splat, pair_pixel)
    # pairs below alpha 1/255 are skipped: they leave T as it is
    contributes = alpha >= ALPHA_MIN
    log_one_minus = torch.log1p(-torch.where(contributes, alpha, 0).double())
    include = ((_log_transmittance(log_one_minus, pair_pixel, log_t)
                + log_one_minus > math.log(TRANSMITTANCE_MIN) + STOP_LOG_MARGIN)
               & ~stopped[pair_pixel])
    stops = _counts(pair_pixel, stopped.shape[0], ~include)
    return pair_splat, pair_pixel, include & contributes, stopped | (stops > 0)


def _compacted(mask: torch.Tensor, count: int) -> torch.Tensor:
    """The positions of the ``count`` true entries of ``mask``, in order, without waiting
    for the device (``nonzero`` would read the count itself)."""
    slot = torch.where(mask, torch.cumsum(mask, 0) - 1, count)   # false ones: a spare slot
    out = torch.empty(count + 1, dtype=torch.long, device=mask.device)
    out.scatter_(0, slot, torch.arange(mask.shape[0], device=mask.device))
    return out[:count]


def _log_transmittance(log_one_minus: torch.Tensor, pair_pixel: torch.Tensor,
                      log_t: torch.Tensor) -> torch.Tensor:
    """log T before each pair: the pixel's running log T plus an exclusive segmented cumsum
    of log(1 - alpha) over its earlier pairs (pairs sorted by pixel, float64; a global cumsum
    minus its value at each pixel's first pair)."""
    running = torch.cumsum(log_one_minus, 0) - log_one_minus                 # exclusive
    pairs_per_pixel = _counts(pair_pixel, log_t.shape[0])
    segment_first = torch.cumsum(pairs_per_pixel, 0) - pairs_per_pixel
    return running - running[segment_first[pair_pixel]] + log_t[pair_pixel]


class _TileGrid:
    """tile_size x tile_size pixel tiles of N images of (H, W); global tile id =
    camera * tiles_per_camera + row * tiles_x + column."""

    def __init__(self, height: int, width: int, tile_size: int, num_cameras: int):
        self.tile_size = tile_size
        self.tiles_x = -(-width // tile_size)
        self.tiles_y = -(-height // tile_size)
        self.tiles_per_camera = self.tiles_x * self.tiles_y
        self.num_cameras = num_cameras
        self.num_tiles = num_cameras * self.tiles_per_camera

    def column(self, u: torch.Tensor) -> torch.Tensor:
        # A monotone clamped floor: u in [lo, hi] implies column(lo) <= column(u) <= column(hi).
        # Any value, NaN too, gives a valid index: input checks are read only after binning.
        return torch.floor(u / self.tile_size).nan_to_num(0.0).clamp(0, self.tiles_x - 1).long()

    def row(self, v: torch.Tensor) -> torch.Tensor:
        return torch.floor(v / self.tile_size).nan_to_num(0.0).clamp(0, self.tiles_y - 1).long()

    @torch.no_grad()
    def bin_pixels(self, pixel_uv, pixel_camera, active):
        """Active pixels grouped by tile: (pixel ids sorted by tile [P], pixels per tile
        [num_tiles], first position of each tile in that list [num_tiles]). Inactive pixels
        sort last under a tile id past the end and are counted nowhere, so the shapes do not
        depend on how many are active (nothing waits for that count)."""
        tile = (pixel_camera * self.tiles_per_camera
                + self.row(pixel_uv[:, 1]) * self.tiles_x + self.column(pixel_uv[:, 0]))
        tile = torch.where(active, tile, self.num_tiles)
        order = torch.argsort(tile, stable=True)
        count = _counts(tile, self.num_tiles + 1)[:-1]
        return order, count, torch.cumsum(count, 0) - count


@torch.no_grad()
def _splat_tiles(splats: Splats, grid: _TileGrid, boxes, total: int):
    """Every (splat, tile) pair where the splat's alpha >= 1/255 box touches the tile,
    sorted by splat; boxes: each splat's box of tiles (row0, row1, col0, col1) [S] long;
    total = the number of those pairs (both from _visible_splats).
    -> st_splat [T] long, st_tile [T] long (global tile id)."""
    device = splats.mean2d.device
    row0, row1, col0, col1 = boxes
    span = col1 - col0 + 1
    tiles_of_splat = span * (row1 - row0 + 1)
    st_splat = torch.repeat_interleave(torch.arange(len(splats), device=device), tiles_of_splat,
                                       output_size=total)
    local = torch.arange(total, device=device) - torch.repeat_interleave(
        torch.cumsum(tiles_of_splat, 0) - tiles_of_splat, tiles_of_splat, output_size=total)
    st_tile = (splats.camera[st_splat] * grid.tiles_per_camera
               + (row0[st_splat] + local // span[st_splat]) * grid.tiles_x
               + col0[st_splat] + local % span[st_splat])
    return st_splat, st_tile


def _candidate_pairs(st_splat, st_tile, pixels_by_tile, tile_count, tile_first, start, stop):
    """The (splat, pixel) pairs at positions [start, stop) of the list of every binned pixel
    of each (splat, tile) pair in order: a shape the caller knows, so nothing here waits."""
    count = tile_count[st_tile]
    end = torch.cumsum(count, 0)                          # past each (splat, tile)'s pixels
    position = torch.arange(start, stop, device=st_splat.device)
    entry = torch.searchsorted(end, position, right=True)
    offset = position - (end - count).index_select(0, entry)
    pair_pixel = pixels_by_tile[tile_first[st_tile.index_select(0, entry)] + offset]
    return st_splat.index_select(0, entry), pair_pixel


def _pair_alpha(params, pixel_uv, pair_splat, pair_pixel):
    """alpha = min(0.99, o exp(-power)) of each (splat, pixel) pair. -> [M].

    params [S, 6] = (u, v, cov_xy, cov_yy, det, opacity) per splat (one gather per pair).
    """
    u, v, cov_xy, cov_yy, det, opacity = params.index_select(0, pair_splat).unbind(-1)
    uv = pixel_uv.index_select(0, pair_pixel)
    power = splat_power(cov_xy, cov_yy, det, uv[:, 0] - u, uv[:, 1] - v)
    return (opacity * torch.exp(-power)).clamp_max(ALPHA_MAX)


class _PairWeightedSum(torch.autograd.Function):
    """out[p] = sum over pairs m with pixel[m] = p of weight[m] * values[splat[m]].

    weight [M], values [S, D], pixel [M], splat [M] long (each (pixel, splat) at most once),
    num_pixels -> out [P, D]. The pairs form a sparse [P, S] matrix in CSR form, so forward
    is one sparse x dense product, d/dvalues the transposed product and d/dweight a sampled
    dense product; no [M, D] tensor is ever built (this is ~10x faster than gathering).
    """

    @staticmethod
    def forward(ctx, weight, values, pixel, splat, num_pixels):
        ctx.shape = (num_pixels, values.shape[0])
        if weight.shape[0] == 0:
            ctx.mark_non_differentiable()
            ctx.save_for_backward(weight, values)
            return values.new_zeros(num_pixels, values.shape[1])
        by_pixel = torch.argsort(pixel, stable=True)   # rows; splat order kept within a row
        matrix = _csr(pixel[by_pixel], splat[by_pixel], weight[by_pixel], ctx.shape)
        ctx.save_for_backward(weight, values, by_pixel, pixel, splat)
        return matrix @ values

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        if len(ctx.saved_tensors) == 2:
            weight, values = ctx.saved_tensors
            return torch.zeros_like(weight), torch.zeros_like(values), None, None, None
        weight, values, by_pixel, pixel, splat = ctx.saved_tensors
        grad_weight = grad_values = None
        grad_out = grad_out.contiguous()
        if ctx.needs_input_grad[0]:
            pattern = _csr(pixel[by_pixel], splat[by_pixel], torch.zeros_like(weight), ctx.shape)
            sampled = torch.sparse.sampled_addmm(pattern, grad_out, values.t().contiguous())
            grad_weight = torch.empty_like(weight)
            grad_weight[by_pixel] = sampled.values()
        if ctx.needs_input_grad[1]:
            by_splat = torch.argsort(splat, stable=True)
            transposed = _csr(splat[by_splat], pixel[by_splat], weight[by_splat],
                              (ctx.shape[1], ctx.shape[0]))
            grad_values = transposed @ grad_out
        return grad_weight, grad_values, None, None, None


def _counts(index: torch.Tensor, size: int, where: torch.Tensor | None = None) -> torch.Tensor:
    """bincount of indices known to lie in [0, size) (only those with ``where`` true, if
    given), without the host read of their maximum that bincount makes on CUDA."""
    ones = torch.ones_like(index) if where is None else where.long()
    return torch.zeros(size, dtype=torch.long, device=index.device).index_add_(0, index, ones)


def _csr(rows, cols, vals, shape):
    """CSR matrix from row-sorted (row, col, value) triples."""
    crow = torch.zeros(shape[0] + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.cumsum(_counts(rows, shape[0]), 0)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, cols, vals, shape, check_invariants=CHECK_CSR)


def later_batch_candidates(device) -> int:
    """Candidate pairs per chunk of what follows the first depth batch: BATCH_MEMORY_SHARE
    of the device's memory (the GPU's, or the host's for the CPU), at least CANDIDATE_CHUNK."""
    if LATER_CANDIDATE_CHUNK is not None:
        return LATER_CANDIDATE_CHUNK
    device = torch.device(device)
    if device.type == "cuda":
        memory = torch.cuda.get_device_properties(device).total_memory
    else:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return max(CANDIDATE_CHUNK, int(BATCH_MEMORY_SHARE * memory / BYTES_PER_CANDIDATE))


def _check_inputs(means, scales, rotations, opacities, features, cam_from_ego, intrinsics,
                  pixels, image_hw, near, tile_size):
    """Clear errors for malformed shapes; returns (H, W, checks): the value checks as
    (message, device flag true if failed), for the caller to read with its first sizes."""
    _check_shapes(means, scales, rotations, opacities, features)
    named = {"means": means, "scales": scales, "rotations": rotations, "opacities": opacities,
             "features": features}
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
    for i, p in enumerate(pixels):
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"pixels[{i}] must be [P, 2] (u, v), got {tuple(p.shape)}")
        if p.device != means.device:
            raise ValueError(f"pixels[{i}] is on {p.device}, Gaussians on {means.device}")
    # Every value check is a flag on the device, read with the renderer's first sizes: no
    # wait for the device of its own.
    checks = [(f"{name} contains NaN or inf", ~torch.isfinite(t).all())
              for name, t in named.items()]
    rot = cam_from_ego[:, :3, :3].double()
    eye = torch.eye(3, dtype=torch.float64, device=rot.device)
    k = intrinsics.double()
    checks += [
        ("cam_from_ego must be rigid (orthonormal rotation, det +1)",
         (rot @ rot.transpose(1, 2) - eye).abs().gt(1e-3).any()
         | (torch.linalg.det(rot) - 1).abs().gt(1e-3).any()),
        ("intrinsics must have positive focal lengths", (k[:, 0, 0] <= 0).any()
         | (k[:, 1, 1] <= 0).any()),
        ("intrinsics with skew are not supported", (k[:, 0, 1].abs() > 1e-6 * k[:, 0, 0]).any())]
    checks += [(f"pixels[{i}] must be finite and inside [0, W={width}] x [0, H={height}]",
                ~(torch.isfinite(p).all() & (p >= 0).all() & (p[:, 0] <= width).all()
                  & (p[:, 1] <= height).all())) for i, p in enumerate(pixels) if p.shape[0]]
    return height, width, [(message, flag.to(means.device)) for message, flag in checks]


def _raise_failed(checks, failed) -> None:
    """ValueError with the message of the first failed check (failed: the flags, read)."""
    for (message, _), bad in zip(checks, failed):
        if bad:
            raise ValueError(message)


def _check_shapes(means, scales, rotations, opacities, features) -> None:
    """Clear errors for Gaussians of mismatched shapes, dtypes or devices."""
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
