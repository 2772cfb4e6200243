"""Frames, poses and projection matrices (NumPy, float64). Conventions used everywhere:

* Quaternions are (w, x, y, z), as in nuScenes. Rotation matrices act on column vectors.
* ``ego`` is base_link of one frame (x forward, y left, z up). ``global`` is the map frame.
* A pose ``T_a_from_b`` is a 4x4 matrix taking homogeneous points in frame b to frame a.
  nuScenes ``ego_pose`` is ``T_global_from_ego``; ``calibrated_sensor`` is ``T_ego_from_cam``.
* ``ego2img`` (4x4) takes a point in one frame's ego coordinates to ``(u*d, v*d, d, 1)``
  where (u, v) are pixels of the *network input* image (after resize/crop) and d the camera
  depth. It is ``[[K', 0], [0, 1]] @ T_cam_from_ego`` with K' the adjusted intrinsics.
* The ego warp from the current frame 0 to a history frame -i is
  ``T_ego(-i)_from_ego(0) = inv(T_global_from_ego(-i)) @ T_global_from_ego(0)`` (paper: P_-i^-1 P_0).
"""
from __future__ import annotations

import numpy as np

RIGID_TOL = 1e-3   # rotations from float32 data or rounded calibration files pass


def quaternion_to_matrix(q) -> np.ndarray:
    """(w, x, y, z) -> 3x3 rotation. Normalises; raises on a zero or non-finite quaternion."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"invalid quaternion {q}")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(R) -> np.ndarray:
    """3x3 rotation -> (w, x, y, z) with w >= 0 (Shepperd's method, stable for all angles).
    Raises ValueError on a matrix that is not a finite rotation (within RIGID_TOL): its
    "quaternion" would be NaN or a silently different rotation."""
    R = np.asarray(R, dtype=np.float64)
    if not _is_rotation(R, RIGID_TOL):
        raise ValueError(f"not a rotation matrix (finite, orthonormal, det +1): {R.tolist()}")
    trace = np.trace(R)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def make_transform(rotation, translation) -> np.ndarray:
    """4x4 from a quaternion (w, x, y, z) or a 3x3 matrix, and a translation."""
    rotation = np.asarray(rotation, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(rotation) if rotation.shape == (4,) else rotation
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def invert_transform(T) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (uses R^T, exact for orthonormal R). Raises
    ValueError on anything else (NaN, a scaled or sheared rotation): R^T would silently be
    the wrong inverse."""
    T = np.asarray(T, dtype=np.float64)
    if not is_rigid(T):
        raise ValueError(f"not a rigid transform (finite 4x4, orthonormal rotation with "
                         f"det +1, last row 0 0 0 1): {T.tolist()}")
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return inv


def is_rigid(T, tol: float = RIGID_TOL) -> bool:
    """True if T is a finite 4x4 rigid transform (orthonormal rotation with det +1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return False
    # np.allclose's test (atol 1e-8, rtol 1e-5) written out: the node checks every pose
    # and extrinsic of every set, and allclose / det cost ~60 us a call
    return _is_rotation(T[:3, :3], tol) and bool(
        (np.abs(T[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all())


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3 = np.eye(3)


def _is_rotation(R: np.ndarray, tol: float) -> bool:
    if R.shape != (3, 3) or not np.isfinite(R).all():
        return False
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return bool((np.abs(R @ R.T - _EYE3) <= tol + 1e-5 * _EYE3).all() and abs(det - 1) < tol)


def rigid_mask(T, tol: float = RIGID_TOL) -> np.ndarray:
    """bool [...] of a stack [..., 4, 4]: which are finite rigid transforms (``is_rigid``'s
    test, vectorised: the node checks a dozen matrices a set, ~15 us a call one by one)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"expected [..., 4, 4] transforms, got {T.shape}")
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(T).all(axis=(-2, -1))
        R = T[..., :3, :3]
        orthonormal = (np.abs(R @ np.swapaxes(R, -1, -2) - _EYE3)
                       <= tol + 1e-5 * _EYE3).all(axis=(-2, -1))
        det = (R[..., 0, 0] * (R[..., 1, 1] * R[..., 2, 2] - R[..., 1, 2] * R[..., 2, 1])
               - R[..., 0, 1] * (R[..., 1, 0] * R[..., 2, 2] - R[..., 1, 2] * R[..., 2, 0])
               + R[..., 0, 2] * (R[..., 1, 0] * R[..., 2, 1] - R[..., 1, 1] * R[..., 2, 0]))
        last_row = (np.abs(T[..., 3, :] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all(axis=-1)
    return finite & orthonormal & (np.abs(det - 1) < tol) & last_row


def invert_transforms(T) -> np.ndarray:
    """Inverses of a stack [..., 4, 4] of rigid transforms (R^T, -R^T t), one vectorised
    computation; raises ValueError naming the first one that is not rigid."""
    T = np.asarray(T, dtype=np.float64)
    rigid = rigid_mask(T)
    if not rigid.all():
        bad = tuple(int(i) for i in np.argwhere(~rigid)[0])
        raise ValueError(f"transform {bad} is not rigid (finite 4x4, orthonormal rotation "
                         f"with det +1, last row 0 0 0 1): {T[bad].tolist()}")
    inv = np.zeros_like(T)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    inv[..., :3, :3] = R_t
    inv[..., :3, 3] = -(R_t @ T[..., :3, 3:])[..., 0]
    inv[..., 3, 3] = 1.0
    return inv


def invert_projections(matrices) -> np.ndarray:
    """The inverses of [N, 4, 4] projections (ego2img: img2ego); NaN for a singular one (its
    camera then observes nothing: the visibility reads no voxel through NaN geometry)."""
    matrices = np.asarray(matrices, dtype=np.float64)
    try:
        return np.linalg.inv(matrices)
    except np.linalg.LinAlgError:
        out = np.full_like(matrices, np.nan)
        for i, m in enumerate(matrices):
            try:
                out[i] = np.linalg.inv(m)
            except np.linalg.LinAlgError:
                pass
        return out

def ego_to_image(intrinsics, T_ego_from_cam) -> np.ndarray:
    """4x4 ``ego2img`` from 3x3 intrinsics (of the network input) and the camera extrinsics."""
    P = np.eye(4)
    P[:3, :3] = np.asarray(intrinsics, dtype=np.float64)
    return P @ invert_transform(T_ego_from_cam)


def ego_warp(T_global_from_ego_current, T_global_from_ego_past) -> np.ndarray:
    """``T_ego(past)_from_ego(current)`` = P_past^-1 P_current (paper Sec. 3.3)."""
    return invert_transform(T_global_from_ego_past) @ np.asarray(T_global_from_ego_current)


def yaw_of(T) -> float:
    """Heading (rotation about z) of a 4x4 transform or 3x3 rotation."""
    R = np.asarray(T)[:3, :3]
    return float(np.arctan2(R[1, 0], R[0, 0]))


def inside_bev_range(points, pc_range) -> np.ndarray:
    """[N, >=2] x, y (ego frame) -> [N] bool: inside the grid's bird's-eye range
    [x_min, x_max) x [y_min, y_max) of ``pc_range`` (x_min, y_min, z_min, x_max, y_max, z_max)."""
    points = np.asarray(points)
    x_min, y_min, _, x_max, y_max, _ = pc_range
    return ((points[:, 0] >= x_min) & (points[:, 0] < x_max)
            & (points[:, 1] >= y_min) & (points[:, 1] < y_max))
