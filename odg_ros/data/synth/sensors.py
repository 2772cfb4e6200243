"""Ray grids of the two sensor kinds and the cell rectangles primitives can cover in them."""
from __future__ import annotations

import numpy as np

from . import sensor_rig
from .primitives import Primitives
from .scene_raycast import Hits, cast, rect_pairs

NEAR = 0.05
# corner index pairs of the 12 edges of Primitives.corners() (corner k has bits x=k>>2, y=k>>1&1, z=k&1)
_BOX_EDGES = np.array([(a, a | bit) for a in range(8) for bit in (1, 2, 4) if not a & bit])


_PIXEL_RAYS = {}


def pixel_rays(K, hw) -> np.ndarray:
    """Unit ray directions [H*W, 3] in the camera frame through pixel centres (u+0.5, v+0.5).
    Cached per (K, hw); do not modify the result."""
    key = (tuple(np.round(np.asarray(K, float).ravel(), 9)), tuple(hw))
    if key not in _PIXEL_RAYS:
        if len(_PIXEL_RAYS) > 64:
            _PIXEL_RAYS.clear()
        _PIXEL_RAYS[key] = _pixel_rays(K, hw)
    return _PIXEL_RAYS[key]


def _pixel_rays(K, hw) -> np.ndarray:
    h, w = hw
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    d = np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def render_camera(prims: Primitives, T_global_from_cam, K, hw, max_dist=250.0):
    """Cast every pixel of a pinhole camera. Returns (Hits, global ray dirs [H*W, 3])."""
    h, w = hw
    R = T_global_from_cam[:3, :3]
    origin = T_global_from_cam[:3, 3]
    dirs = pixel_rays(K, hw) @ R.T
    centre_dist = np.linalg.norm(prims.center - origin, axis=1) - np.linalg.norm(prims.half, axis=1)
    cand = np.flatnonzero(centre_dist < max_dist)
    cam = (prims.take(cand).corners() - origin) @ R                # camera frame [C, 8, 3]
    # the box clipped by the near plane: corners in front + edge crossings of the plane
    ea, eb = _BOX_EDGES[:, 0], _BOX_EDGES[:, 1]
    za, zb = cam[:, ea, 2], cam[:, eb, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = (NEAR - za) / (zb - za)
    cross = ((za - NEAR) * (zb - NEAR) < 0)[..., None]
    pts = np.concatenate([cam, cam[:, ea] + f[..., None] * (cam[:, eb] - cam[:, ea])], 1)
    valid = np.concatenate([cam[..., 2] >= NEAR, cross[..., 0]], 1)
    z = np.maximum(pts[..., 2], NEAR)
    u = K[0, 0] * pts[..., 0] / z + K[0, 2]
    v = K[1, 1] * pts[..., 1] / z + K[1, 2]
    big = 1e9
    c0 = np.floor(np.where(valid, u, big).min(1))
    c1 = np.ceil(np.where(valid, u, -big).max(1)) + 1
    r0 = np.floor(np.where(valid, v, big).min(1))
    r1 = np.ceil(np.where(valid, v, -big).max(1)) + 1
    keep = valid.any(1)
    c0, c1 = np.clip(c0, 0, w).astype(np.int64), np.clip(c1, 0, w).astype(np.int64)
    r0, r1 = np.clip(r0, 0, h).astype(np.int64), np.clip(r1, 0, h).astype(np.int64)
    r1 = np.where(keep, r1, r0)
    ray, prim = rect_pairs(r0, r1, c0, c1, w)
    prim = cand[prim].astype(np.int32)
    return cast(prims, origin, dirs, ray, prim), dirs


def lidar_grid_dirs() -> np.ndarray:
    """Unit directions [32 * A, 3] of the LiDAR's beams x azimuth columns in the LiDAR frame,
    row-major (beam, column); column c has azimuth -pi + (c + 0.5) * 2 pi / A."""
    el = np.deg2rad(sensor_rig.LIDAR_ELEVATIONS_DEG)[:, None]
    az = -np.pi + (np.arange(sensor_rig.LIDAR_AZIMUTHS) + 0.5) * 2 * np.pi / sensor_rig.LIDAR_AZIMUTHS
    az = az[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)
    return d.reshape(-1, 3)


_LIDAR_DIRS = lidar_grid_dirs()


def scan_lidar(prims: Primitives, T_global_from_lidar):
    """Cast one LiDAR sweep (instantaneous). Returns (Hits, global dirs, lidar-frame dirs)."""
    n_el, n_az = len(sensor_rig.LIDAR_ELEVATIONS_DEG), sensor_rig.LIDAR_AZIMUTHS
    R = T_global_from_lidar[:3, :3]
    origin = T_global_from_lidar[:3, 3]
    dirs_l = _LIDAR_DIRS
    dirs = dirs_l @ R.T
    corners = (prims.corners() - origin) @ R                      # LiDAR frame [P, 8, 3]
    cxy = corners[..., :2].mean(1)
    rxy = np.linalg.norm(corners[..., :2] - cxy[:, None], axis=2).max(1)
    d = np.linalg.norm(cxy, axis=1)
    zmin, zmax = corners[..., 2].min(1), corners[..., 2].max(1)
    dmin = np.maximum(d - rxy, 1e-3)
    dmax = d + rxy
    el_hi = np.where(zmax > 0, np.arctan2(zmax, dmin), np.arctan2(zmax, dmax))
    el_lo = np.where(zmin < 0, np.arctan2(zmin, dmin), np.arctan2(zmin, dmax))
    el = np.deg2rad(sensor_rig.LIDAR_ELEVATIONS_DEG)
    step = el[1] - el[0]
    r0 = np.clip(np.floor((el_lo - el[0]) / step), 0, n_el).astype(np.int64)
    r1 = np.clip(np.ceil((el_hi - el[0]) / step) + 1, 0, n_el).astype(np.int64)
    az_c = np.arctan2(cxy[:, 1], cxy[:, 0])
    with np.errstate(invalid="ignore"):
        half = np.where(d > rxy, np.arcsin(np.clip(rxy / np.maximum(d, 1e-9), 0, 1)), np.pi)
    col = lambda a: (a + np.pi) / (2 * np.pi) * n_az - 0.5
    full = half >= np.pi - 1e-9
    c0 = np.where(full, 0, np.floor(col(az_c - half))).astype(np.int64)
    c1 = np.where(full, n_az, np.ceil(col(az_c + half)) + 1).astype(np.int64)
    c1 = np.minimum(c1, c0 + n_az)
    keep = dmin < sensor_rig.LIDAR_MAX_RANGE
    r1 = np.where(keep, r1, r0)
    ray, prim = rect_pairs(r0, r1, c0, c1, n_az, wrap=True)
    hits = cast(prims, origin, dirs, ray, prim, max_t=sensor_rig.LIDAR_MAX_RANGE)
    return hits, dirs, dirs_l


def lidar_points(world, prims: Primitives, hits: Hits, dirs_global, dirs_lidar, origin, rng):
    """Returned points of one sweep in nuScenes layout.

    Returns (points float32 [N, 5] = x, y, z, intensity, ring in the LiDAR frame, ordered by
    azimuth column then beam; lidarseg index uint8 [N]; thing index int32 [N], -1 for stuff).
    Range noise sigma 2 cm; intensity from the material's reflectivity and incidence angle.
    """
    from . import materials as M
    from .scene_raycast import GROUND
    from .world import GROUND_SEG, NO_PAINT

    n_el, n_az = len(sensor_rig.LIDAR_ELEVATIONS_DEG), sensor_rig.LIDAR_AZIMUTHS
    order = np.arange(n_el * n_az).reshape(n_el, n_az).T.ravel()   # column-major firing order
    t = hits.t[order]
    valid = np.isfinite(t) & (t >= sensor_rig.LIDAR_MIN_RANGE) & (t <= sensor_rig.LIDAR_MAX_RANGE)
    sel = order[valid]
    t = t[valid] + rng.normal(0, 0.02, len(sel))
    prim = hits.prim[sel]
    seg = np.zeros(len(sel), np.uint8)
    inst = np.full(len(sel), -1, np.int32)
    refl = np.zeros(len(sel))
    obj = prim >= 0
    seg[obj] = prims.seg[prim[obj]]
    inst[obj] = prims.inst[prim[obj]]
    refl_table = np.zeros(256)
    for m, r in M.REFLECTIVITY.items():
        refl_table[m] = r
    refl[obj] = refl_table[prims.material[prim[obj]]]
    g = prim == GROUND
    if g.any():
        p = origin[None, :2] + hits.t[sel[g], None] * dirs_global[sel[g], :2]
        mat, paint = world.ground_at(p[:, 0], p[:, 1])
        seg[g] = GROUND_SEG[mat]
        refl[g] = np.where(paint != NO_PAINT, M.PAINT_REFLECTIVITY, refl_table[mat])
    cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal[sel].astype(float), dirs_global[sel]))
    intensity = np.clip(refl * (0.35 + 0.65 * cos_inc) + rng.normal(0, 1.5, len(sel)), 0, 255)
    xyz = dirs_lidar[sel] * t[:, None]
    ring = (sel // n_az).astype(np.float64)
    points = np.concatenate([xyz, intensity[:, None], ring[:, None]], 1).astype(np.float32)
    return points, seg, inst
