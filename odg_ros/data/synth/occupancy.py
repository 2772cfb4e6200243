"""Occ3D-style ground truth of a keyframe: semantic voxels and visibility masks.

Grid (docs/architecture.md sec. 1): [-40, -40, -1, 40, 40, 5.4] m in the keyframe's ego frame,
200 x 200 x 16 voxels of 0.4 m indexed [x, y, z], 17 = free.

* semantics: surfaces, as Occ3D builds them from accumulated LiDAR returns. The flat ground
  (z = 0) labels the voxel layer that contains it with the ground class under the column
  centre; a primitive labels every voxel its surface passes through: the voxel centre lies
  within half a voxel of the solid but not deeper than half a voxel inside it (for boxes
  exactly the voxels the box boundary overlaps). Solid interiors (inside buildings, trucks)
  stay free, and unobserved. Objects overwrite stuff, stuff overwrites the ground.
* masks: a voxel is observed if a sensor ray reaches or hits it. LiDAR: every return's ray
  is traversed through the grid (Amanatides-Woo, vectorised over rays) from the sensor to
  the voxel holding the point, as in Occ3D. Cameras: each voxel is tested along the camera
  pixel ray through its centre against that pixel's ray-cast depth (a dense depth map of the
  true geometry): observed if its centre is no more than half a voxel diagonal behind the
  first surface. (Traversing the GT grid per pixel instead stops every grazing ray at the
  first ground voxel and leaves the far road striped with unobserved voxels.)
"""
from __future__ import annotations

import numpy as np

from ...classes import FREE_LABEL
from ...geometry import invert_transform
from .primitives import Primitives, contains
from .world import GROUND_CLASS, World

GRID_MIN = np.array([-40.0, -40.0, -1.0])
GRID_MAX = np.array([40.0, 40.0, 5.4])
VOXEL = 0.4
GRID_SHAPE = (200, 200, 16)
THING_LABELS = np.arange(11)  # Occ3D labels 0..10 are objects


def voxel_centres_ego(index) -> np.ndarray:
    """Centres [..., 3] (ego frame) of integer voxel indices [..., 3]."""
    return (np.asarray(index) + 0.5) * VOXEL + GRID_MIN


def voxelize(world: World, prims: Primitives, T_global_from_ego) -> np.ndarray:
    """uint8 [200, 200, 16] semantics of the world (at the primitives' time) in the ego frame."""
    X, Y, Z = GRID_SHAPE
    sem = np.full(GRID_SHAPE, FREE_LABEL, np.uint8)
    T = np.asarray(T_global_from_ego, float)
    # ground layer
    ground_z_ego = -T[2, 3]  # the ground is the global plane z = 0; the ego is level
    k_ground = int(np.floor((ground_z_ego - GRID_MIN[2]) / VOXEL))
    if 0 <= k_ground < Z:
        c = (np.arange(X) + 0.5) * VOXEL + GRID_MIN[0]
        gx, gy = np.meshgrid(c, (np.arange(Y) + 0.5) * VOXEL + GRID_MIN[1], indexing="ij")
        pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(X * Y), np.ones(X * Y)], 1) @ T.T
        mat, _ = world.ground_at(pts[:, 0], pts[:, 1])
        sem[:, :, k_ground] = GROUND_CLASS[mat].reshape(X, Y)
    if not len(prims):
        return sem
    # primitives: candidate voxels from each primitive's ego-frame bounding box
    T_ego_from_global = invert_transform(T)
    corners = prims.corners() @ T_ego_from_global[:3, :3].T + T_ego_from_global[:3, 3]
    lo = np.floor((corners.min(1) - VOXEL / 2 - GRID_MIN) / VOXEL).astype(np.int64)
    hi = np.floor((corners.max(1) + VOXEL / 2 - GRID_MIN) / VOXEL).astype(np.int64) + 1
    lo = np.clip(lo, 0, GRID_SHAPE)
    hi = np.clip(hi, 0, GRID_SHAPE)
    size = np.maximum(hi - lo, 0)
    counts = size.prod(1)
    is_thing = np.isin(prims.label, THING_LABELS)
    for group in (np.flatnonzero(~is_thing & (counts > 0)), np.flatnonzero(is_thing & (counts > 0))):
        if not len(group):
            continue
        cnt = counts[group]
        prim = np.repeat(group, cnt)
        off = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        sz = size[prim]
        i = lo[prim, 0] + off // (sz[:, 1] * sz[:, 2])
        j = lo[prim, 1] + (off // sz[:, 2]) % sz[:, 1]
        k = lo[prim, 2] + off % sz[:, 2]
        centres = voxel_centres_ego(np.stack([i, j, k], 1)) @ T[:3, :3].T + T[:3, 3]
        # the voxel overlaps the surface: its centre is within half a voxel of the solid but
        # not deeper than half a voxel inside it (primitives thinner than a voxel are all surface)
        near = contains(prims, centres, prim, inflate=VOXEL / 2)
        thick = np.flatnonzero(near & (prims.half[prim].min(1) > VOXEL / 2))
        deep = np.zeros(len(prim), bool)
        deep[thick] = contains(prims, centres[thick], prim[thick], inflate=-VOXEL / 2)
        surface = near & ~deep
        sem[i[surface], j[surface], k[surface]] = prims.label[prim[surface]]
    return sem


def traverse(occupied: np.ndarray, origins, dirs, max_t=None, return_hits=False, stop_at_occupied=True):
    """Voxels visited by rays (Amanatides-Woo) in a grid of GRID_SHAPE.

    occupied: bool [X, Y, Z]; origins [R, 3] or [3] and unit dirs [R, 3] in the grid's (ego)
    frame, metres; max_t [R] metres (None: unbounded). A ray visits voxels from its origin
    until it has marked the first occupied voxel (only with ``stop_at_occupied``), passed
    max_t (a voxel counts when the ray enters it at t <= max_t) or left the grid. Rays whose
    origin is outside the grid are ignored. Returns bool [X, Y, Z]; with ``return_hits`` also
    float64 [R]: the distance (metres) at which each ray enters its first occupied voxel (inf
    if it has none before max_t / the grid boundary).
    """
    shape = np.array(occupied.shape)
    visited = np.zeros(occupied.size, bool)
    occ_flat = occupied.ravel()
    dirs = np.asarray(dirs, float).reshape(-1, 3)
    origins = np.broadcast_to(np.asarray(origins, float), dirs.shape)
    n = len(dirs)
    max_t = np.full(n, np.inf) if max_t is None else np.asarray(max_t, float)
    pos = (origins - GRID_MIN) / VOXEL                       # voxel units
    idx = np.floor(pos).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < shape), axis=1) & np.all(np.isfinite(dirs), axis=1)
    idx, pos, d, t_max = idx[ok], pos[ok], dirs[ok], max_t[ok] / VOXEL
    t_hit = np.full(n, np.inf)
    rid = np.flatnonzero(ok)
    X, Y, Z = (int(v) for v in shape)
    cols = []
    for a in range(3):
        da = d[:, a]
        step = np.where(da > 0, 1, -1).astype(np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.where(da != 0, 1.0 / np.where(da != 0, da, 1.0), np.inf)
            t_next = np.where(da != 0, ((idx[:, a] + (step > 0)) - pos[:, a]) * inv, np.inf)
        cols.append((idx[:, a].copy(), step, t_next, np.abs(inv)))
    (ix, sx, tx, dx), (iy, sy, ty, dy), (iz, sz, tz, dz) = cols
    flat = (ix * Y + iy) * Z + iz
    t_entry = np.zeros(len(flat))
    fx, fy = sx * (Y * Z), sy * Z
    while len(flat):
        reach = t_entry <= t_max
        visited[flat[reach]] = True
        stop = occ_flat[flat]
        alive = reach & ~stop if stop_at_occupied else reach
        if return_hits:
            h = reach & stop
            t_hit[rid[h]] = t_entry[h] * VOXEL
        mx = (tx <= ty) & (tx <= tz)
        my = ~mx & (ty <= tz)
        mz = ~(mx | my)
        t_entry = np.where(mx, tx, np.where(my, ty, tz))
        ix += sx * mx
        iy += sy * my
        iz += sz * mz
        flat += fx * mx + fy * my + sz * mz
        tx += np.where(mx, dx, 0)
        ty += np.where(my, dy, 0)
        tz += np.where(mz, dz, 0)
        alive &= (ix >= 0) & (ix < X) & (iy >= 0) & (iy < Y) & (iz >= 0) & (iz < Z)
        if not alive.all():
            k = np.flatnonzero(alive)
            ix, iy, iz, sx, sy, sz = ix[k], iy[k], iz[k], sx[k], sy[k], sz[k]
            tx, ty, tz, dx, dy, dz = tx[k], ty[k], tz[k], dx[k], dy[k], dz[k]
            flat, t_entry, t_max, fx, fy, rid = flat[k], t_entry[k], t_max[k], fx[k], fy[k], rid[k]
    visited = visited.reshape(occupied.shape)
    return (visited, t_hit) if return_hits else visited


_ALL_CENTRES = voxel_centres_ego(np.indices(GRID_SHAPE).reshape(3, -1).T)  # [X*Y*Z, 3], C order


def camera_mask(hits_t, hits_normal, pixel_dirs, K, hw, T_ego_from_cam) -> np.ndarray:
    """bool [200, 200, 16]: voxels one camera observes.

    From a dense ray cast of the camera: ``hits_t`` [H*W] distance along each pixel's unit
    ray (inf: sky), ``hits_normal`` [H*W, 3] surface normals and ``pixel_dirs`` [H*W, 3] unit
    ray directions (both in the frame of T_ego_from_cam's target, i.e. rotated like the
    rays), for intrinsics K and size hw. A voxel centre projecting into pixel p is observed
    when it lies no more than half a voxel diagonal behind p's surface, measured along the
    voxel's own ray to the surface's tangent plane (exact for planes such as the ground,
    where the pixel's neighbouring rays meet the surface metres apart)."""
    h, w = hw
    centres = _ALL_CENTRES
    R, o = T_ego_from_cam[:3, :3], T_ego_from_cam[:3, 3]
    p = (centres - o) @ R                                   # camera frame
    z = p[:, 2]
    front = np.flatnonzero(z > 0.05)
    u = np.floor(K[0, 0] * p[front, 0] / z[front] + K[0, 2]).astype(np.int64)
    v = np.floor(K[1, 1] * p[front, 1] / z[front] + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    front, u, v = front[inside], u[inside], v[inside]
    pix = v * w + u
    rel = centres[front] - o
    dist = np.linalg.norm(rel, axis=1)
    dir_v = rel / dist[:, None]
    t_pix = np.asarray(hits_t)[pix]
    n = np.asarray(hits_normal, float)[pix]
    along = np.einsum("ij,ij->i", np.asarray(pixel_dirs)[pix], n)     # pixel ray . normal
    denom = np.einsum("ij,ij->i", dir_v, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.where(np.abs(denom) > 0.005, t_pix * along / denom, t_pix)
    t_plane = np.where(np.isfinite(t_pix) & (t_plane > 0), t_plane, t_pix)
    seen = dist <= t_plane + VOXEL * np.sqrt(3) / 2
    mask = np.zeros(centres.shape[0], bool)
    mask[front[seen]] = True
    return mask.reshape(GRID_SHAPE)
