"""The renderer tests' camera, random Gaussian scenes and a float64 per-pixel reference of
alpha compositing with gsplat's conventions."""
from __future__ import annotations

import math

import numpy as np
import torch

HW = (128, 352)
K = np.array([[250.0, 0.0, 176.0], [0.0, 250.0, 64.0], [0.0, 0.0, 1.0]])
NEAR = 0.05


# ----------------------------------------------------------------------------- reference
def reference_render(means, scales, rotations, opacities, features, cam_from_ego, K, pixels,
                     hw, near=NEAR, dtype=np.float64):
    """Textbook splatting, one pixel at a time over every Gaussian, NumPy float64 (or
    np.longdouble where the textbook determinant a c - b^2 cancels badly).

    Sigma = R S^2 R^T, 2D cov = J W Sigma W^T J^T + 0.3 I (J at the fov-clamped mean),
    det clamped at 1e-10, conic = inverse; per pixel: all Gaussians with z > near sorted by z
    (stable), power = 0.5 d^T conic d, skip power < 0 or alpha < 1/255, alpha capped at 0.99,
    stop (exclusive) once T (1 - alpha) <= 1e-4. Returns depth [P], features [P, C], alpha [P].
    """
    means, scales, rotations, opacities, features, cam_from_ego, K, pixels = (
        np.asarray(a, dtype=dtype) for a in
        (means, scales, rotations, opacities, features, cam_from_ego, K, pixels))
    height, width = hw
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W_rot, W_t = cam_from_ego[:3, :3], cam_from_ego[:3, 3]
    lim_x = ((width - cx) / fx + 0.3 * 0.5 * width / fx, cx / fx + 0.3 * 0.5 * width / fx)
    lim_y = ((height - cy) / fy + 0.3 * 0.5 * height / fy, cy / fy + 0.3 * 0.5 * height / fy)
    splats = []  # (z, index, u, v, conic, opacity)
    for g in range(means.shape[0]):
        q = rotations[g]
        n = np.linalg.norm(q)
        w, x, y, z = (1.0, 0.0, 0.0, 0.0) if n <= 1e-12 else q / n
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        sigma = R @ np.diag(scales[g] ** 2) @ R.T
        pc = W_rot @ means[g] + W_t
        if pc[2] <= near:
            continue
        tx = np.clip(pc[0] / pc[2], -lim_x[1], lim_x[0])
        ty = np.clip(pc[1] / pc[2], -lim_y[1], lim_y[0])
        J = np.array([[fx / pc[2], 0, -fx * tx / pc[2]], [0, fy / pc[2], -fy * ty / pc[2]]])
        cov = J @ W_rot @ sigma @ W_rot.T @ J.T + 0.3 * np.eye(2)
        det = max(cov[0, 0] * cov[1, 1] - cov[0, 1] * cov[1, 0], 1e-10)
        conic = (cov[1, 1] / det, -cov[0, 1] / det, cov[0, 0] / det)
        u, v = fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy
        splats.append((pc[2], g, u, v, conic, opacities[g]))
    splats.sort(key=lambda s: (s[0], s[1]))
    values = [np.concatenate([features[s[1]], [s[0], 1.0]]) for s in splats]
    out = np.zeros((pixels.shape[0], features.shape[1] + 2), dtype=dtype)
    for p, (pu, pv) in enumerate(pixels):
        transmittance = 1.0
        for s, value in zip(splats, values):
            du, dv = s[2] - pu, s[3] - pv
            a, b, c = s[4]
            power = 0.5 * (a * du * du + c * dv * dv) + b * du * dv
            if power < 0:
                continue
            alpha = min(0.99, s[5] * np.exp(-power))
            if alpha < 1.0 / 255.0:
                continue
            next_t = transmittance * (1 - alpha)
            if next_t <= 1e-4:
                break
            out[p] += transmittance * alpha * value
            transmittance = next_t
    out = out.astype(np.float64)
    return out[:, -2], out[:, :-2], out[:, -1]


# ----------------------------------------------------------------------------- helpers
def look_transform(yaw, pitch, position):
    """A rigid cam_from_ego: camera at `position` (ego), looking along ego yaw/pitch."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                        math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    ego_from_cam = np.eye(4)
    ego_from_cam[:3, :3] = np.stack([right, down, forward], axis=1)
    ego_from_cam[:3, 3] = position
    return np.linalg.inv(ego_from_cam)


def random_scene(seed, num_gaussians, num_pixels, dtype=torch.float64, num_classes=5,
                 dense=False):
    """Gaussians scattered mostly in front of a randomly posed camera (some behind / aside).
    dense: larger, more opaque Gaussians, so that most pixels hit the 1e-4 early stop."""
    rng = np.random.default_rng(seed)
    cam_from_ego = look_transform(rng.uniform(-np.pi, np.pi), rng.uniform(-0.2, 0.2),
                                  rng.uniform(-2, 2, 3))
    ego_from_cam = np.linalg.inv(cam_from_ego)
    cam_pts = np.stack([rng.uniform(-8, 8, num_gaussians), rng.uniform(-3, 3, num_gaussians),
                        rng.uniform(-2, 20, num_gaussians)], axis=1)
    means = cam_pts @ ego_from_cam[:3, :3].T + ego_from_cam[:3, 3]
    scene = dict(
        means=means,
        scales=np.exp(rng.uniform(np.log(0.03), np.log(1.0), (num_gaussians, 3))) * (
            3.0 if dense else 1.0),
        rotations=rng.normal(size=(num_gaussians, 4)),
        opacities=rng.uniform(0.5 if dense else 0.0, 1.0, num_gaussians),
        features=rng.uniform(0.0, 1.0, (num_gaussians, num_classes)),
    )
    tensors = {k: torch.tensor(v, dtype=dtype) for k, v in scene.items()}
    pixels = torch.tensor(rng.uniform(0, 1, (num_pixels, 2)) * [HW[1], HW[0]], dtype=dtype)
    return tensors, torch.tensor(cam_from_ego, dtype=dtype), torch.tensor(K, dtype=dtype), pixels
