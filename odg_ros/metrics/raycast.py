"""Ray casting through occupancy grids for RayIoU (SparseOcc convention, docs/architecture.md sec. 6).

Rays are cast in *voxel units*: a point p in metres is ``(p - grid_min) / voxel_size`` in the
grid, so voxel (i, j, k) is the unit cube [i, i+1) x [j, j+1) x [k, k+1). Voxels are cubes, so a
distance in voxel units times ``voxel_size`` is a distance in metres.

Traversal is Amanatides-Woo (one voxel at a time along the ray), vectorised over all rays at
once with NumPy. A ray stops at the first voxel whose label is not free; its depth is the
distance from the ray origin to where the ray *leaves* that voxel (SparseOcc records the
traversal distance at the voxel's exit). A ray that leaves the grid without a hit reports
"no hit" and the distance at which it left the grid.

Conventions where SparseOcc's CUDA/C++ marcher is ambiguous (all of measure zero for the
LiDAR pattern, but they decide hand-made test cases):
* a voxel the ray only touches at an edge or corner (zero-length chord) is not visited: when
  the ray crosses two or three voxel planes at the same distance (within 1e-9 voxel) all those
  axes step together (SparseOcc steps one axis at a time and can visit such a voxel);
* an origin on a voxel face (within 1e-9 voxel, along the axes the ray moves on) starts in
  the voxel the ray moves into; a ray lying in a face (direction component 0 on that axis)
  belongs to the voxel on the + side (floor);
* an origin outside the grid starts where the ray enters the grid (SparseOcc starts from the
  origin's voxel truncated towards zero with C ``int()``; that differs only for an origin with
  a negative grid coordinate, i.e. below the grid, since origins keep |x|, |y| < 39 m).
"""
from __future__ import annotations

import math

import numpy as np

# Two plane crossings closer than this (in voxel units) count as one: the voxel between them
# has a zero-length chord and is not visited.
TIE_EPS = 1e-9


def lidar_ray_directions() -> np.ndarray:
    """The SparseOcc LiDAR pattern: 39 pitch angles x 360 azimuths -> unit vectors [14040, 3].

    Pitch k = 0..9 is -(pi/2 - atan(k + 1)) (steep to shallow downward rays); then the last
    spacing is repeated until the pitch exceeds 0.21 rad (the top of the nuScenes LiDAR's field
    of view). Azimuths are 0, 1, ..., 359 degrees. Order: pitch-major, azimuth-minor.
    """
    pitches = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while pitches[-1] < 0.21:
        pitches.append(pitches[-1] + (pitches[-1] - pitches[-2]))
    pitch = np.asarray(pitches, dtype=np.float64)[:, None]
    azimuth = np.deg2rad(np.arange(360, dtype=np.float64))[None, :]
    directions = np.stack(np.broadcast_arrays(np.cos(pitch) * np.cos(azimuth),
                                              np.cos(pitch) * np.sin(azimuth),
                                              np.sin(pitch) + 0 * azimuth), axis=-1)
    return directions.reshape(-1, 3)


def _grid_entry_exit(origins, directions, shape):
    """Slab test against the box [0, X] x [0, Y] x [0, Z] -> (t_enter >= 0, t_exit) [R]."""
    size = np.asarray(shape, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / directions
        t_low = (0.0 - origins) * inv
        t_high = (size - origins) * inv
    moving = directions != 0
    inside_slab = (origins >= 0) & (origins < size)
    # An axis the ray does not move along either never constrains it or always excludes it.
    t_near = np.where(moving, np.minimum(t_low, t_high), np.where(inside_slab, -np.inf, np.inf))
    t_far = np.where(moving, np.maximum(t_low, t_high), np.where(inside_slab, np.inf, -np.inf))
    t_enter = np.maximum(t_near.max(axis=1), 0.0)
    t_exit = t_far.min(axis=1)
    return t_enter, t_exit


def cast_rays(occupied_bits: np.ndarray, origins: np.ndarray, directions: np.ndarray,
              num_bits: int = 1):
    """First voxel hit along each ray, for up to 8 occupancy layers traversed together.

    Args:
        occupied_bits: uint8 [X, Y, Z]; bit g set where layer g (e.g. g=0 prediction, g=1 GT)
            is occupied. Sharing one traversal keeps the cost of scoring two grids close to one.
        origins: float [R, 3] ray origins in voxel units (may lie outside the grid).
        directions: float [R, 3] unit directions (voxel units = metres / voxel_size, so unit
            length in metres is unit length here).
        num_bits: number of layers G (1..8).

    Returns:
        hit_index: int64 [G, R] flat index (x * Y * Z + y * Z + z) of the first occupied voxel
            of layer g, -1 where the ray leaves the grid (or never enters it) without a hit.
        hit_depth: float64 [G, R] distance in voxel units from the origin to where the ray
            leaves the hit voxel; for no hit, where it leaves the grid (0 if it never enters).
    """
    bits = np.ascontiguousarray(occupied_bits, dtype=np.uint8)
    if bits.ndim != 3:
        raise ValueError(f"occupied_bits must be [X, Y, Z], got shape {bits.shape}")
    if not 1 <= num_bits <= 8:
        raise ValueError(f"num_bits must be in 1..8, got {num_bits}")
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ValueError(f"origins {origins.shape} and directions {directions.shape} differ")
    if not (np.isfinite(origins).all() and np.isfinite(directions).all()):
        raise ValueError("ray origins and directions must be finite")
    norms = np.linalg.norm(directions, axis=1)
    if directions.size and np.abs(norms - 1.0).max() > 1e-6:
        raise ValueError("ray directions must be unit vectors")
    directions = np.where(directions == 0, 0.0, directions)  # -0.0 -> +0.0 (sign of 1/d)

    X, Y, Z = bits.shape
    R = origins.shape[0]
    hit_index = np.full((num_bits, R), -1, dtype=np.int64)
    t_enter, t_exit = _grid_entry_exit(origins, directions, bits.shape)
    hit_depth = np.repeat(np.where(t_enter < t_exit, t_exit, 0.0)[None], num_bits, axis=0)

    rays = np.flatnonzero(t_enter < t_exit - TIE_EPS)   # a shorter chord only touches the grid
    if rays.size == 0:
        return hit_index, hit_depth
    o = origins[rays]
    d = directions[rays]
    start = o + t_enter[rays, None] * d
    # A start within TIE_EPS of a voxel plane it moves across lies on it: metres -> voxel
    # units rounds (an origin on a voxel corner in metres comes out ~1e-14 off it), and the
    # ray would otherwise "hit" the voxel it is leaving at depth ~1e-14.
    plane = np.round(start)
    start = np.where((d != 0) & (np.abs(start - plane) <= TIE_EPS), plane, start)
    # Start voxel: the one the ray moves into (matters when the start lies on a voxel face).
    voxel = np.where(d >= 0, np.floor(start), np.ceil(start) - 1.0)
    voxel = np.clip(voxel, 0, np.asarray([X - 1, Y - 1, Z - 1], dtype=np.float64))
    step = np.where(d >= 0, 1.0, -1.0)
    with np.errstate(divide="ignore"):
        inv = 1.0 / d  # +inf on axes the ray does not move along (d was made +0.0)
    # Distance to the next plane on axis a = (voxel_a + next_offset_a) * inv_a, computed afresh
    # each step from the integer voxel index (no accumulated rounding).
    next_offset = np.where(d >= 0, 1.0, 0.0) - o

    # Per-ray state as separate contiguous columns (faster than [R, 3] slices).
    vx, vy, vz = voxel[:, 0].copy(), voxel[:, 1].copy(), voxel[:, 2].copy()
    sx, sy, sz = step[:, 0].copy(), step[:, 1].copy(), step[:, 2].copy()
    ix, iy, iz = inv[:, 0].copy(), inv[:, 1].copy(), inv[:, 2].copy()
    nx, ny, nz = next_offset[:, 0].copy(), next_offset[:, 1].copy(), next_offset[:, 2].copy()
    t_end = t_exit[rays] - TIE_EPS
    found = np.zeros(rays.size, dtype=np.uint8)
    all_found = np.uint8((1 << num_bits) - 1)
    flat = bits.ravel()
    yz, zz = float(Y * Z), float(Z)

    while rays.size:
        tx = (vx + nx) * ix
        ty = (vy + ny) * iy
        tz = (vz + nz) * iz
        t_leave = np.minimum(np.minimum(tx, ty), tz)  # where the ray leaves the current voxel
        index = (vx * yz + vy * zz + vz).astype(np.int64)
        code = flat[index]
        new = code & ~found
        if new.any():
            for g in range(num_bits):
                first = (new >> g) & 1 == 1
                if first.any():
                    hit_index[g, rays[first]] = index[first]
                    hit_depth[g, rays[first]] = t_leave[first]
            found |= code
        done = (found == all_found) | (t_leave >= t_end)
        if done.sum() * 8 >= done.size:
            keep = ~done  # many rays finished: drop them from every column
            rays, tx, ty, tz, t_leave = rays[keep], tx[keep], ty[keep], tz[keep], t_leave[keep]
            vx, vy, vz, sx, sy, sz = vx[keep], vy[keep], vz[keep], sx[keep], sy[keep], sz[keep]
            ix, iy, iz, nx, ny, nz = ix[keep], iy[keep], iz[keep], nx[keep], ny[keep], nz[keep]
            t_end, found = t_end[keep], found[keep]
        elif done.any():
            # Few finished: park them in place (no step, nothing left to find) instead of
            # gathering every column; the next big drop removes them.
            sx[done] = sy[done] = sz[done] = 0.0
            found[done] = all_found
            t_end[done] = -np.inf
        # Step every axis whose plane is crossed at t_leave (ties step together).
        limit = t_leave + TIE_EPS
        vx += sx * (tx <= limit)
        vy += sy * (ty <= limit)
        vz += sz * (tz <= limit)
    return hit_index, hit_depth
