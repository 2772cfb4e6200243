"""3D Gaussians (ego frame) -> 2D screen-space splats per camera (EWA splatting).

Conventions follow gsplat / the Inria 3DGS rasteriser:

* camera frame is OpenCV (x right, y down, z forward); a point projects to
  (fx x/z + cx, fy y/z + cy) and pixel (i, j) has its centre at (j + 0.5, i + 0.5);
* a Gaussian is culled when its camera depth z <= near;
* 2D covariance = J W Sigma W^T J^T + 0.3 px^2 on the diagonal (the anti-aliasing blur), where
  J is the Jacobian of the projection at the mean, with x/z and y/z clamped to 1.3x the
  field of view first (the mean itself is not clamped);
* the depth d_i of a splat is the camera-space z of its mean.

Numerical care beyond the reference code: Sigma = M M^T with M = R diag(s), so the 2x2
covariance is A A^T with A = J W M (2x3) and its determinant |A_u x A_v|^2 (Lagrange's
identity) can never come out negative by cancellation; the blurred determinant is then
>= 0.09 px^4 without clamping (we still clamp, as gsplat does, to 1e-10).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..rotation import normalise_quaternions

BLUR_PX2 = 0.3            # added to the 2D covariance diagonal (px^2)
FOV_CLAMP_MARGIN = 0.3    # x/z clamped to the image extent + 0.3 * tan(fov / 2) (~1.3x fov)
ALPHA_MIN = 1.0 / 255.0   # contributions below this alpha are skipped
ALPHA_MAX = 0.99          # alpha is capped here (Inria); keeps log(1 - alpha) finite
DET_MIN = 1e-10


def quaternion_to_rotation(unit_quaternions: torch.Tensor) -> torch.Tensor:
    """[G, 4] unit (w, x, y, z) -> [G, 3, 3] rotation matrices (act on column vectors)."""
    w, x, y, z = unit_quaternions.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*unit_quaternions.shape[:-1], 3, 3)


@dataclass
class Splats:
    """Projected (camera, Gaussian) splats; project_gaussians returns the visible ones sorted
    by camera depth (stable: ties keep the Gaussian order). S = number of splats.

    camera [S] long, gaussian [S] long: which camera / input Gaussian each splat comes from.
    mean2d [S, 2]: projected centre (u, v) in pixels.
    cov_xx, cov_xy, cov_yy [S]: blurred 2D covariance (px^2); det [S] its determinant.
    depth [S]: camera-space z of the mean (metres). opacity [S].
    half_extent [S, 2] (no gradient): half-size (u, v) of the box outside of which the splat's
        alpha is below 1/255, i.e. exactly where it can contribute (<= 3.33 sigma).
    overflow [] bool (no gradient): some visible splat has a non-finite 2D mean or covariance
        (scales or positions out of range); the renderer raises when it reads its sizes.
    """

    camera: torch.Tensor
    gaussian: torch.Tensor
    mean2d: torch.Tensor
    cov_xx: torch.Tensor
    cov_xy: torch.Tensor
    cov_yy: torch.Tensor
    det: torch.Tensor
    depth: torch.Tensor
    opacity: torch.Tensor
    half_extent: torch.Tensor
    overflow: torch.Tensor

    def __len__(self) -> int:
        return int(self.camera.shape[0])

    def take(self, index: torch.Tensor) -> "Splats":
        """The splats at ``index`` [S'] long, in that order."""
        return Splats(**{name: value if name == "overflow" else value[index]
                         for name, value in vars(self).items()})


def splat_power(cov_xy: torch.Tensor, cov_yy: torch.Tensor, det: torch.Tensor,
                delta_u: torch.Tensor, delta_v: torch.Tensor) -> torch.Tensor:
    """0.5 * delta^T cov^-1 delta (the Gaussian's exponent), all arguments of one shape.

    Written as a sum of two non-negative terms (completing the square in u), so it never
    goes negative through cancellation for elongated splats (the reference code's
    "power > 0" skip can then not fire spuriously); cov_yy >= 0.3 keeps it bounded.
    """
    shifted = delta_u - (cov_xy / cov_yy) * delta_v
    return 0.5 * ((cov_yy / det) * shifted * shifted + delta_v * delta_v / cov_yy)


def project_gaussians(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor,
                      opacities: torch.Tensor, cam_from_ego: torch.Tensor,
                      intrinsics: torch.Tensor, image_hw, near: float,
                      gaussian_scene: torch.Tensor | None = None,
                      cameras_per_scene: int | None = None) -> Splats:
    """Project G Gaussians into N cameras; keep the splats that can touch the image.

    Arguments as project_candidates. Returns the visible splats, sorted by depth.
    """
    candidates, visible = project_candidates(means, scales, rotations, opacities, cam_from_ego,
                                             intrinsics, image_hw, near, gaussian_scene,
                                             cameras_per_scene)
    return candidates.take(depth_order(candidates, visible)[:int(visible.sum())])


def depth_order(candidates: Splats, visible: torch.Tensor) -> torch.Tensor:
    """Order of the candidates with the visible ones first, sorted by depth (stable), as
    project_gaussians returns them."""
    with torch.no_grad():
        return torch.argsort(torch.where(visible, candidates.depth,
                                         torch.full_like(candidates.depth, math.inf)), stable=True)


@torch.no_grad()
def _camera_gaussian_pairs(means, opacities, cam_rot, cam_t, near, gaussian_scene,
                           cameras_per_scene):
    """(camera [S], gaussian [S], candidate [S] bool) of every (camera, Gaussian) pair in
    row-major order (nonzero's order); candidate: in front of the near plane and not
    transparent. All pairs, the others marked: a shape known without reading a count."""
    if gaussian_scene is None:
        z_all = torch.einsum("nj,gj->ng", cam_rot[:, 2], means) + cam_t[:, None, 2]
    else:       # [M, G]: each Gaussian against its own scene's M cameras
        z_axis = cam_rot[:, 2].view(-1, cameras_per_scene, 3)[gaussian_scene]   # [G, M, 3]
        z_all = (torch.einsum("gmj,gj->mg", z_axis, means)
                 + cam_t[:, 2].view(-1, cameras_per_scene)[gaussian_scene].t())
    candidate = ((z_all > near) & (opacities >= ALPHA_MIN)[None, :]).flatten()
    rows, num_gaussians = z_all.shape
    camera = torch.arange(rows, device=means.device).repeat_interleave(
        num_gaussians, output_size=rows * num_gaussians)
    gaussian = torch.arange(num_gaussians, device=means.device).repeat(rows)
    if gaussian_scene is not None:
        camera = gaussian_scene[gaussian] * cameras_per_scene + camera
    return camera, gaussian, candidate


def project_candidates(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor,
                       opacities: torch.Tensor, cam_from_ego: torch.Tensor,
                       intrinsics: torch.Tensor, image_hw, near: float,
                       gaussian_scene: torch.Tensor | None = None,
                       cameras_per_scene: int | None = None) -> tuple[Splats, torch.Tensor]:
    """Project G Gaussians into N cameras: every (camera, Gaussian) pair, camera-major, and
    which of them are visible.

    means [G, 3] (ego, m), scales [G, 3] (m), rotations [G, 4] (w, x, y, z), opacities [G],
    cam_from_ego [N, 4, 4], intrinsics [N, 3, 3], image_hw (H, W). Returns (Splats of the
    pairs, visible [S] bool). Visible: in front of the near plane, opacity >= 1/255, and the
    splat's alpha >= 1/255 box touches the image [0, W] x [0, H]; only visible pairs carry
    meaningful values.
    gaussian_scene [G] long, cameras_per_scene M (optional, together): K = N / M independent
    scenes, scene k seen by cameras k M ... (k + 1) M - 1 only; a Gaussian is projected into
    its own scene's cameras.
    """
    height, width = image_hw
    rot = quaternion_to_rotation(normalise_quaternions(rotations))
    factor = rot * scales[:, None, :]                                  # M = R diag(s), [G, 3, 3]

    cam_rot = cam_from_ego[:, :3, :3]                                  # [N, 3, 3]
    cam_t = cam_from_ego[:, :3, 3]                                     # [N, 3]
    camera, gaussian, candidate = _camera_gaussian_pairs(means, opacities, cam_rot, cam_t,
                                                         near, gaussian_scene,
                                                         cameras_per_scene)
    r = cam_rot[camera]                                                # [S0, 3, 3]
    p = torch.einsum("sij,sj->si", r, means[gaussian]) + cam_t[camera]
    factor_cam = torch.einsum("sij,sjk->sik", r, factor[gaussian])     # W M, [S0, 3, 3]
    x, y, z = p.unbind(-1)
    # pairs that are no candidates (behind the near plane, transparent) get a harmless
    # depth, so that nothing computed for them, gradients included, is inf or NaN
    z = torch.where(candidate, z, 1.0)

    k = intrinsics[camera]
    fx, fy, cx, cy = k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2]
    mean2d = torch.stack([fx * x / z + cx, fy * y / z + cy], dim=-1)

    # Jacobian at the mean with x/z, y/z clamped to ~1.3x the field of view (gsplat): keeps
    # splats far outside the image from getting absurd covariances.
    margin_x = FOV_CLAMP_MARGIN * 0.5 * width / fx
    margin_y = FOV_CLAMP_MARGIN * 0.5 * height / fy
    xz = torch.maximum(torch.minimum(x / z, (width - cx) / fx + margin_x), -(cx / fx + margin_x))
    yz = torch.maximum(torch.minimum(y / z, (height - cy) / fy + margin_y), -(cy / fy + margin_y))
    # Rows of A = J W M: J_u = (fx/z) (1, 0, -x/z), J_v = (fy/z) (0, 1, -y/z).
    a_u = (fx / z)[:, None] * (factor_cam[:, 0] - xz[:, None] * factor_cam[:, 2])
    a_v = (fy / z)[:, None] * (factor_cam[:, 1] - yz[:, None] * factor_cam[:, 2])
    cov_xx = (a_u * a_u).sum(-1)
    cov_xy = (a_u * a_v).sum(-1)
    cov_yy = (a_v * a_v).sum(-1)
    det_unblurred = torch.linalg.cross(a_u, a_v).pow(2).sum(-1)       # >= 0 exactly
    det = (det_unblurred + BLUR_PX2 * (cov_xx + cov_yy) + BLUR_PX2 * BLUR_PX2).clamp_min(DET_MIN)
    cov_xx = cov_xx + BLUR_PX2
    cov_yy = cov_yy + BLUR_PX2

    opacity = opacities[gaussian]
    with torch.no_grad():
        # alpha >= 1/255  <=>  power <= log(255 opacity) =: r^2 / 2; the ellipse
        # delta^T cov^-1 delta <= r^2 has half-widths r sqrt(cov_xx), r sqrt(cov_yy).
        # A small margin: the exact alpha test of every candidate pair decides anyway.
        r2 = 2.0 * torch.log(opacity * (1.0 / ALPHA_MIN)).clamp_min(0.0)
        half_extent = torch.stack([(r2 * cov_xx).sqrt(), (r2 * cov_yy).sqrt()], dim=-1)
        half_extent = half_extent * 1.001 + 0.01
        lo = mean2d - half_extent
        hi = mean2d + half_extent
        visible = (candidate & (hi[:, 0] >= 0) & (lo[:, 0] <= width) & (hi[:, 1] >= 0)
                   & (lo[:, 1] <= height))
        # read together with the renderer's first size, not on its own
        overflow = (~(torch.isfinite(mean2d).all(-1) & torch.isfinite(det)) & visible).any()
    return Splats(camera=camera, gaussian=gaussian, mean2d=mean2d, cov_xx=cov_xx, cov_xy=cov_xy,
                  cov_yy=cov_yy, det=det, depth=z, opacity=opacity, half_extent=half_extent,
                  overflow=overflow), visible

