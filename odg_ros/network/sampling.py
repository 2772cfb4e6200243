"""4D (multi-view, multi-frame, multi-scale) feature sampling with motion compensation.

Paper Sec. 3.3; OPUS/SparseBEV "adaptive spatio-temporal sampling":
1. around each query's centroid, G x P points (offsets from a zero-initialised linear layer
   with bias U(-0.5, 0.5), scaled by the spread = std of the query's previous means; a query
   with a single mean samples at its centroid);
2. per history frame t, dynamic queries move the point back along their velocity
   (x_t = x_0 - v_x (t_0 - t_t), y likewise, z unchanged: Eq. 7-8);
3. every point is carried into frame t's ego frame by the ego warp P_t^-1 P_0 and projected
   with that frame's cameras (ego2img);
4. each point reads the first camera it is visible in, bilinearly on every FPN level, and the
   levels are mixed by softmax weights; a point visible in no camera contributes zeros.

Feature layouts for sampling (one tensor per level; a single grid_sample call samples every
view, frame and group: no Python loop, no 5-D blow-up):
- plain, [T*B*G, C/G, N, H, W], frame-major: the camera axis is the depth axis of a 5-D
  grid_sample, addressed exactly at slice centres;
- camera rows (the fast path, ``camera_rows_layout``), [F*B*G, C/G, N*(H+1), W] in
  channels-last memory: the cameras stacked along the image rows, each below one zero row.
  A 2-D bilinear read there equals the per-camera read with zero padding, borders included
  (the zero row stands in for the padding above a camera and below the one before it), and
  on CPU it is several times faster than the 3-D read. The node's step (the feature ring)
  always reads camera rows; the plain layout stays as the tests' reference.
Either layout may hold F distinct frames in any order (a ring buffer of cached history, or a
history still filling up); ``frame_index`` [T] says which of them each time step reads.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

DEPTH_EPS = 1e-5


def sampling_centres(prev_means: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """prev_means [B, Q, K, 3] -> centroid [B, Q, 3], spread [B, Q, 3] (0 when K == 1)."""
    centroid = prev_means.mean(dim=2)
    if prev_means.shape[2] == 1:
        return centroid, torch.zeros_like(centroid)
    return centroid, prev_means.std(dim=2)


def warp_points(points: torch.Tensor, velocity: torch.Tensor | None, time_delta: torch.Tensor,
                ego_warp: torch.Tensor | None) -> torch.Tensor:
    """Motion-compensate sampling points into every history frame's ego coordinates.

    points [B, Q, M, 3] (current ego frame), velocity [B, Q, 2] m/s or None,
    time_delta [B, T] = t_0 - t_t (s), ego_warp [B, T, 4, 4] = T_ego(t)_from_ego(0) or None
    -> [B, Q, T, M, 3] in each frame's own ego coordinates.
    """
    B, Q, M, _ = points.shape
    T = time_delta.shape[1]
    with torch.autocast(points.device.type, enabled=False):
        points, velocity, time_delta, ego_warp = full_precision(points, velocity, time_delta,
                                                                ego_warp)
        pts = points.unsqueeze(2).expand(B, Q, T, M, 3)
        if velocity is not None:
            shift = velocity[:, :, None, None, :] * time_delta[:, None, :, None, None]
            pts = torch.cat([pts[..., :2] - shift, pts[..., 2:]], dim=-1)   # [B,Q,T,M,3]
        if ego_warp is not None:
            R = ego_warp[:, None, :, None, :3, :3]                      # [B,1,T,1,3,3]
            t = ego_warp[:, None, :, None, :3, 3]
            pts = (R @ pts.unsqueeze(-1)).squeeze(-1) + t
    return pts


def full_precision(*tensors):
    """Geometry runs in float32 (float64 stays), never in half precision, whatever autocast
    is active: bf16 keeps 8 bits, i.e. +-0.16 m at 40 m and up to ~6 px of projection error
    across a 704 px image. None passes through."""
    return [t if t is None or t.dtype == torch.float64 else t.float() for t in tensors]


def first_visible_camera(points: torch.Tensor, ego2img: torch.Tensor, image_hw):
    """points [B, Q, T, M, 3] (frame-t ego), ego2img [B, T, N, 4, 4]
    -> pixel u, v [B, T, Q, M] in the first camera that sees the point, that camera's index
       (long) and the visibility mask [B, T, Q, M] (u, v, camera are arbitrary where False)."""
    H, W = image_hw
    with torch.autocast(points.device.type, enabled=False):      # see full_precision
        points, ego2img = full_precision(points, ego2img)
        R = ego2img[..., :3, :3]                                        # [B, T, N, 3, 3]
        t = ego2img[..., :3, 3]
        cam = torch.einsum("btnij,bqtmj->btnqmi", R, points) + t[:, :, :, None, None, :]
    depth = cam[..., 2]
    safe_depth = depth.clamp(min=DEPTH_EPS)
    u = cam[..., 0] / safe_depth
    v = cam[..., 1] / safe_depth
    visible = (depth > DEPTH_EPS) & (u >= 0) & (u < W) & (v >= 0) & (v < H)  # [B,T,N,Q,M]
    camera = visible.to(torch.uint8).argmax(dim=2, keepdim=True)        # first camera seeing it
    u = u.gather(2, camera).squeeze(2)
    v = v.gather(2, camera).squeeze(2)
    return u, v, camera.squeeze(2), visible.any(dim=2)


def project_to_cameras(points: torch.Tensor, ego2img: torch.Tensor, image_hw):
    """points [B, Q, T, M, 3] (frame-t ego), ego2img [B, T, N, 4, 4]
    -> normalised grid coords [B, T, Q, M, 3] (x, y in [-1, 1], z = camera slice centre)
       and visibility mask [B, T, Q, M] (True where some camera sees the point)."""
    H, W = image_hw
    N = ego2img.shape[2]
    u, v, camera, any_visible = first_visible_camera(points, ego2img, image_hw)
    z = (2.0 * camera.to(u.dtype) + 1.0) / N - 1.0
    grid = torch.stack([u / W * 2.0 - 1.0, v / H * 2.0 - 1.0, z], dim=-1)
    grid = torch.where(any_visible.unsqueeze(-1), grid, torch.full_like(grid, -2.0))
    return grid, any_visible


def layout_dtype(dtype: torch.dtype) -> torch.dtype:
    """The sampling layout is never half precision: grid_sample needs the grid in the
    features' dtype, and a bf16 grid over N*(h+1) rows is up to ~0.4 px off (autocast runs
    grid_sample in float32 anyway, by copying half-precision features at every call)."""
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def camera_rows_layout(frames: list[torch.Tensor], num_groups: int,
                       out: torch.Tensor | None = None) -> torch.Tensor:
    """F frames of one level, each [B, N, C, h, w] -> [F*B*G, C/G, N*(h+1), w], channels-last
    memory ([F, B, G, N, h+1, w, C/G]), each camera's rows below one zero row; float32 for
    half-precision input (``layout_dtype``).
    ``out``: write into this tensor (a preallocated ring buffer slot range) instead."""
    F_, (B, N, C, h, w), G = len(frames), frames[0].shape, num_groups
    if out is None:   # only the zero rows need filling: the rest is overwritten
        out = frames[0].new_empty(F_, B, G, N, h + 1, w, C // G,
                                  dtype=layout_dtype(frames[0].dtype))
        out[:, :, :, :, 0] = 0
    else:
        out = out.view(F_, B, G, N, h + 1, w, C // G)
    for f, feats in enumerate(frames):   # one strided copy per frame (F <= a few)
        out[f, :, :, :, 1:] = feats.view(B, N, G, C // G, h, w).permute(0, 2, 1, 4, 5, 3)
    return camera_rows_view(out.view(F_ * B * G, N * (h + 1), w, C // G))


def camera_rows_view(memory: torch.Tensor) -> torch.Tensor:
    """[F*B*G, N*(h+1), w, c] contiguous -> the same memory as [F*B*G, c, N*(h+1), w]."""
    return memory.permute(0, 3, 1, 2)


def camera_rows_grid(u, v, camera, image_hw, num_cams: int, level_hw) -> torch.Tensor:
    """Pixel (u, v) in ``camera`` [...] -> normalised 2-D grid [..., 2] of the camera-rows
    layout of a level of size ``level_hw`` (a pixel outside the image reads zeros)."""
    H, W = image_hw
    h = level_hw[0]
    rows = num_cams * (h + 1)
    # level pixel (align_corners=False) v / H * h - 0.5, shifted below its camera's zero row
    y = camera.to(v.dtype) * (h + 1) + 1.0 + v / H * h - 0.5
    return torch.stack([u / W * 2.0 - 1.0, (y + 0.5) / rows * 2.0 - 1.0], dim=-1)


class SpatioTemporalSampling(nn.Module):
    def __init__(self, embed_dims: int, num_groups: int, num_points: int, num_levels: int):
        super().__init__()
        self.num_groups = num_groups
        self.num_points = num_points
        self.num_levels = num_levels
        self.offsets = nn.Linear(embed_dims, num_groups * num_points * 3)
        self.level_weights = nn.Linear(embed_dims, num_groups * num_points * num_levels)
        nn.init.zeros_(self.offsets.weight)
        nn.init.uniform_(self.offsets.bias, -0.5, 0.5)

    def forward(self, query, prev_means, velocity, mlvl_feats, ego2img, ego_warp, time_delta,
                image_hw, frame_index: torch.Tensor | None = None):
        """query [B, Q, E], prev_means [B, Q, K, 3], velocity [B, Q, 2] | None,
        mlvl_feats L x [F*B*G, c, N, h, w] (plain) or L x [F*B*G, c, N*(h+1), w] (camera rows),
        ego2img [B, F, N, 4, 4], ego_warp [B, F, 4, 4] | None, time_delta [B, F]: the F stored
        frames in their storage order; frame_index [T] long: the stored frame each time step
        reads (None: F = T, in time order) -> sampled features [B, Q, G, T*P, c]."""
        B, Q, _ = query.shape
        G, P, L = self.num_groups, self.num_points, self.num_levels
        centroid, spread = sampling_centres(prev_means)
        offsets = self.offsets(query).view(B, Q, G * P, 3)
        points = centroid.unsqueeze(2) + offsets * spread.unsqueeze(2)  # [B, Q, G*P, 3]
        points = warp_points(points, velocity, time_delta, ego_warp)    # [B, Q, F, G*P, 3]
        weights = self.level_weights(query).view(B, Q, G, 1, P, L).softmax(dim=-1)
        if mlvl_feats[0].dim() == 4:
            sampled = self._sample_camera_rows(points, weights, mlvl_feats, ego2img, image_hw)
        else:
            sampled = self._sample_plain(points, weights, mlvl_feats, ego2img, image_hw)
        if frame_index is not None:                                     # [B, Q, G, F, P, c]
            sampled = sampled.index_select(3, frame_index)
        T, c = sampled.shape[3], sampled.shape[-1]
        return sampled.reshape(B, Q, G, T * P, c)

    def _sample_plain(self, points, weights, mlvl_feats, ego2img, image_hw):
        """The per-camera 3-D formulation -> [B, Q, G, T, P, c]."""
        B, Q = points.shape[:2]
        G, P = self.num_groups, self.num_points
        T = ego2img.shape[1]
        grid, visible = project_to_cameras(points, ego2img, image_hw)   # [B, T, Q, G*P, 3]
        grid = grid.view(B, T, Q, G, P, 3).permute(1, 0, 3, 2, 4, 5)    # [T, B, G, Q, P, 3]
        grid = grid.reshape(T * B * G, Q, P, 1, 3).to(mlvl_feats[0].dtype)
        sampled = 0
        for level, feat in enumerate(mlvl_feats):
            s = F.grid_sample(feat, grid, mode="bilinear", padding_mode="zeros",
                              align_corners=False)                      # [T*B*G, c, Q, P, 1]
            c = s.shape[1]
            s = s.view(T, B, G, c, Q, P).permute(1, 4, 2, 0, 5, 3)      # [B, Q, G, T, P, c]
            sampled = sampled + s * weights[..., level:level + 1]
        mask = visible.view(B, T, Q, G, P).permute(0, 2, 3, 1, 4).unsqueeze(-1)
        return sampled * mask.to(sampled.dtype)

    def _sample_camera_rows(self, points, weights, mlvl_feats, ego2img, image_hw):
        """The fast 2-D formulation over the camera-rows layout -> [B, Q, G, F, P, c]."""
        B, Q = points.shape[:2]
        G, P = self.num_groups, self.num_points
        F_, N = ego2img.shape[1:3]
        u, v, camera, visible = first_visible_camera(points, ego2img, image_hw)  # [B,F,Q,G*P]

        def frame_major(x):                                             # -> [F, B, G, Q, P]
            return x.view(B, F_, Q, G, P).permute(1, 0, 3, 2, 4)
        u, v, camera, visible = map(frame_major, (u, v, camera, visible))
        # a point no camera sees goes far left of every image, where grid_sample reads zeros
        # (so no mask pass over the sampled features is needed)
        u = torch.where(visible, u, torch.full_like(u, -2.0 * image_hw[1]))
        v = torch.where(visible, v, torch.zeros_like(v))
        weights = weights.squeeze(3).permute(4, 0, 2, 1, 3).contiguous()  # [L, B, G, Q, P]
        sampled = None
        for level, feat in enumerate(mlvl_feats):
            rows, w = feat.shape[-2:]
            grid = camera_rows_grid(u, v, camera, image_hw, N, (rows // N - 1, w))
            s = F.grid_sample(feat, grid.reshape(F_ * B * G, Q, P, 2).to(feat.dtype),
                              mode="bilinear", padding_mode="zeros", align_corners=False)
            s = s.permute(0, 2, 3, 1).reshape(F_, B, G, Q, P, s.shape[1])  # [F,B,G,Q,P,c]
            weight = weights[level].unsqueeze(-1)                       # [B, G, Q, P, 1]
            sampled = s * weight if sampled is None else torch.addcmul(sampled, s, weight)
        return sampled.permute(1, 3, 2, 0, 4, 5)                       # [B, Q, G, F, P, c]
