"""gsplat's CUDA operators as the census counts them, on a machine that cannot run them.

gsplat's ``rasterization`` is Python (reshapes, concatenations, its autograd Functions) around
six C++/CUDA operators of its extension ``gsplat.cuda._backend._C``. Inside
``gsplat_kernels_counted_by`` every line of gsplat's Python runs as it is and is counted like
any other code; only the extension is replaced by stand-ins of those operators. Each stand-in
counts the kernels its C++ launches and the host reads it makes (gsplat 1.5.3's
``csrc/*.cpp``, the paths ``rasterization(packed=False)`` takes):

================================  ==========================================  ===========
operator                          kernels launched                            host reads
================================  ==========================================  ===========
projection_ewa_3dgs_fused_fwd     the projection (+ zeros of the               0
                                  compensations when asked)
projection_ewa_3dgs_fused_bwd     zeros of 3 (4 with the view matrices)        0
                                  gradients, the backward kernel
intersect_tile                    tiles per Gaussian, their cumsum, then       1: the number of
                                  (if any) the intersections and their         intersections
                                  radix sort                                   (``.item()``)
intersect_offset                  the offsets kernel                           0
rasterize_to_pixels_3dgs_fwd      the forward kernel                           0
rasterize_to_pixels_3dgs_bwd      zeros of 4 gradients, the backward kernel    0
================================  ==========================================  ===========

Their results have the shapes and dtypes of the real ones; the values are not the
rasteriser's: the projection is gsplat's own PyTorch version (``gsplat.cuda._torch_impl``,
with the kernel's opacity cull) so that the number of intersections is a real one, and the
images and every gradient are zeros. Nothing the census counts depends on them: after the
rasteriser the render loss gathers pixels and sums, with no size read from the device.
"""
from __future__ import annotations

import contextlib
import sys
import types

import torch

ALPHA_THRESHOLD = 1.0 / 255.0          # gsplat's projection culls Gaussians below this opacity


class _StandInExtension:
    """The operators of gsplat's extension that ``rasterization(packed=False)`` calls."""

    class CameraModelType:
        PINHOLE, ORTHO, FISHEYE, FTHETA = "pinhole", "ortho", "fisheye", "ftheta"

    # gsplat looks up the last part of a dotted name on the extension itself
    PINHOLE, ORTHO, FISHEYE, FTHETA = "pinhole", "ortho", "fisheye", "ftheta"

    def __init__(self, mode):
        self.mode = mode

    def projection_ewa_3dgs_fused_fwd(self, means, covars, quats, scales, opacities, viewmats,
                                      Ks, width, height, eps2d, near_plane, far_plane,
                                      radius_clip, calc_compensations, camera_model):
        from gsplat.cuda import _torch_impl
        if covars is not None or camera_model != "pinhole":
            raise NotImplementedError("the stand-in projects quaternions and scales through "
                                      "pinhole cameras (what the render loss uses)")
        batch = means.shape[:-2]
        flat = [t.reshape(-1, *t.shape[len(batch):]) for t in (means, quats, scales, viewmats, Ks)]
        with self.mode.uncounted(), torch.no_grad():
            parts = []           # one image set at a time: gsplat's PyTorch code is [C, N, 3, 3]
            for means_k, quats_k, scales_k, viewmats_k, Ks_k in zip(*flat):
                covars, _ = _torch_impl._quat_scale_to_covar_preci(quats_k, scales_k, True,
                                                                   False)
                parts.append(_torch_impl._fully_fused_projection(
                    means_k, covars, viewmats_k, Ks_k, width, height, eps2d=eps2d,
                    near_plane=near_plane, far_plane=far_plane,
                    calc_compensations=calc_compensations))
            radii, means2d, depths, conics, compensations = (
                None if parts[0][i] is None else
                torch.stack([p[i] for p in parts]).reshape(*batch, *parts[0][i].shape)
                for i in range(5))
            if opacities is not None:
                culled = (opacities < ALPHA_THRESHOLD)[..., None, :, None]
                radii = torch.where(culled, 0, radii)
        self.mode.record(ops=1 + int(calc_compensations))
        return radii.int(), means2d, depths, conics, compensations

    def projection_ewa_3dgs_fused_bwd(self, means, covars, quats, scales, viewmats, Ks, width,
                                      height, eps2d, camera_model, radii, conics,
                                      compensations, v_means2d, v_depths, v_conics,
                                      v_compensations, viewmats_requires_grad):
        with self.mode.uncounted():
            v_means, v_quats, v_scales = (torch.zeros_like(t) for t in (means, quats, scales))
            v_viewmats = torch.zeros_like(viewmats) if viewmats_requires_grad else None
        self.mode.record(ops=4 + int(viewmats_requires_grad))
        return v_means, None, v_quats, v_scales, v_viewmats

    def intersect_tile(self, means2d, radii, depths, image_ids, gaussian_ids, n_images,
                       tile_size, tile_width, tile_height, sort, segmented):
        if image_ids is not None or segmented:
            raise NotImplementedError("the stand-in intersects unpacked, unsegmented splats")
        with self.mode.uncounted():
            low = torch.floor(means2d / tile_size - radii / tile_size).int()
            high = torch.ceil(means2d / tile_size + radii / tile_size).int()
            limit = torch.tensor([tile_width, tile_height], dtype=torch.int32)
            span = (high.clamp(min=0).minimum(limit) - low.clamp(min=0).minimum(limit))
            tiles_per_gauss = span.prod(-1) * (radii > 0).all(-1)
            count = int(tiles_per_gauss.sum()) if tiles_per_gauss.numel() else 0
            isect_ids = torch.zeros(count, dtype=torch.int64, device=means2d.device)
            flatten_ids = torch.zeros(count, dtype=torch.int32, device=means2d.device)
        elements = tiles_per_gauss.numel()
        launches = (2 + (2 if sort else 1) * bool(count)) if elements else 0
        self.mode.record(ops=launches, waits=int(elements > 0), kind="read")
        return tiles_per_gauss.int(), isect_ids, flatten_ids

    def intersect_offset(self, isect_ids, n_images, tile_width, tile_height):
        with self.mode.uncounted():
            offsets = torch.zeros(n_images, tile_height, tile_width, dtype=torch.int32,
                                  device=isect_ids.device)
        self.mode.record(ops=1)
        return offsets

    def rasterize_to_pixels_3dgs_fwd(self, means2d, conics, colors, opacities, backgrounds,
                                     masks, width, height, tile_size, isect_offsets,
                                     flatten_ids):
        images = isect_offsets.shape[:-2]
        with self.mode.uncounted():
            renders = colors.new_zeros(*images, height, width, colors.shape[-1])
            alphas = colors.new_zeros(*images, height, width, 1)
            last_ids = torch.zeros(*images, height, width, dtype=torch.int32,
                                   device=colors.device)
        self.mode.record(ops=1)
        return renders, alphas, last_ids

    def rasterize_to_pixels_3dgs_bwd(self, means2d, conics, colors, opacities, backgrounds,
                                     masks, width, height, tile_size, isect_offsets,
                                     flatten_ids, render_alphas, last_ids, v_render_colors,
                                     v_render_alphas, absgrad):
        with self.mode.uncounted():
            grads = [torch.zeros_like(t) for t in (means2d, conics, colors, opacities)]
            absolute = torch.zeros_like(means2d) if absgrad else None
        self.mode.record(ops=5 + int(absgrad))
        return (absolute, *grads)


@contextlib.contextmanager
def gsplat_kernels_counted_by(mode):
    """gsplat's extension replaced by the stand-ins, counting into ``mode`` (a CensusMode)
    while it is active."""
    import gsplat.cuda  # noqa: F401  (gsplat's Python, without its extension)
    name = "gsplat.cuda._backend"
    saved = sys.modules.get(name)
    stand_in = types.ModuleType(name)
    stand_in._C = _StandInExtension(mode)
    sys.modules[name] = stand_in
    try:
        yield
    finally:
        if saved is None:
            del sys.modules[name]
        else:
            sys.modules[name] = saved
