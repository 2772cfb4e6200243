"""Ray casting through occupancy grids for RayIoU, step for step as SparseOcc's ray caster
(``lib/dvr/dvr.cu``, ``render_forward`` in its test phase), vectorised over all rays with NumPy.

Rays are cast in *voxel units*: a point p in metres is ``(p - grid_min) / voxel_size``, so voxel
(i, j, k) is the cube [i, i+1) x [j, j+1) x [k, k+1). What SparseOcc does, and so this module:

* a ray is given by its origin and an end point one metre away, both rounded to float32
  (``rays_in_voxel_units`` converts metres to voxel units in float64, then rounds); the
  direction is ``(end - origin) / |end - origin|`` in float64 from those float32 values;
* the ray starts in the voxel of C ``int()`` truncation of the origin (towards zero, also for an
  origin outside the grid) and visits it first. An origin on a voxel face therefore starts in
  the voxel on the + side even when the ray leaves through that face: that voxel is visited with
  exit distance 0 (``(v + 0 - o) / d`` is -0.0). A ray lying in a face's plane walks the
  + side row;
* per axis: step +1 if the direction component is >= 0, else -1; tMax = distance to the next
  plane (DBL_MAX for a zero component), tDelta = step / d. Each iteration records the current
  voxel with exit distance min(tMax), then steps ONE axis: x if tMaxX < tMaxY and tMaxX < tMaxZ,
  else y if tMaxY < tMaxZ, else z (ties go to z, then y, strict ``<``), and adds tDelta to that
  axis's tMax (accumulated, not recomputed). Two planes crossed at the same distance therefore
  visit the voxel between them, with a zero-length chord;
* voxels outside the grid are stepped through without being recorded until the ray is inside;
  once it has been inside, leaving ends the ray. At most ``MAX_STEP + 1`` iterations, counted
  from the origin;
* the ray reports the first voxel whose label is not free, with that voxel's exit distance; if
  there is none, the last voxel it visited inside the grid (a free one) and its exit distance,
  i.e. where it left the grid; a ray that never entered reports voxel (0, 0, 0) and distance -1.
"""
from __future__ import annotations

import math

import numpy as np

MAX_STEP = 1000       # SparseOcc ends a ray once its iteration count exceeds this
DBL_MAX = np.finfo(np.float64).max
OUTSIDE = np.uint16(1 << 8)   # the border mark of _march_from_inside's padded grid (above 8 layers)


def lidar_ray_directions() -> np.ndarray:
    """The SparseOcc LiDAR pattern: 39 pitch angles x 360 azimuths -> float32 [14040, 3].

    Pitch k = 0..9 is -(pi/2 - atan(k + 1)) (steep to shallow downward rays); then the last
    spacing is repeated until the pitch exceeds 0.21 rad (the top of the nuScenes LiDAR's field
    of view). Azimuths are 0, 1, ..., 359 degrees. Order: pitch-major, azimuth-minor. Computed
    in float64 and rounded to float32, as SparseOcc keeps them.
    """
    pitches = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while pitches[-1] < 0.21:
        pitches.append(pitches[-1] + (pitches[-1] - pitches[-2]))
    pitch = np.asarray(pitches, dtype=np.float64)[:, None]
    azimuth = np.deg2rad(np.arange(360, dtype=np.float64))[None, :]
    directions = np.stack(np.broadcast_arrays(np.cos(pitch) * np.cos(azimuth),
                                              np.cos(pitch) * np.sin(azimuth),
                                              np.sin(pitch) + 0 * azimuth), axis=-1)
    return directions.reshape(-1, 3).astype(np.float32)


def rays_in_voxel_units(origins, directions, grid_min, voxel_size):
    """Origins [R, 3] (metres) and unit directions [R, 3] -> float32 origins and end points
    [R, 3] in voxel units, rounded where SparseOcc rounds: the end point is origin + direction
    in float64; both are shifted by the float32 grid corner and divided by the float32 voxel
    size in float64, then rounded to float32."""
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions).reshape(-1, 3).astype(np.float64)
    corner = np.asarray(grid_min, dtype=np.float32).astype(np.float64)
    scale = np.float64(np.float32(voxel_size))
    start = ((origins - corner) / scale).astype(np.float32)
    end = ((origins + directions - corner) / scale).astype(np.float32)
    return start, end


def cast_rays(occupied_bits: np.ndarray, origins: np.ndarray, endpoints: np.ndarray,
              num_bits: int = 1):
    """The voxel each ray reports, for up to 8 occupancy layers traversed together.

    Args:
        occupied_bits: uint8 [X, Y, Z]; bit g set where layer g (e.g. g=0 prediction, g=1 GT)
            is occupied. Sharing one traversal keeps the cost of scoring two grids close to one.
        origins, endpoints: [R, 3] ray origins and points on the rays, voxel units; rounded to
            float32 first (SparseOcc's input type). The ray goes from origin through end point.
        num_bits: number of layers G (1..8).

    Returns:
        voxel: int64 [G, R] flat index (x * Y * Z + y * Z + z) of the voxel the ray reports for
            layer g: the first occupied one; else the last one visited inside the grid; 0 when
            the ray never entered the grid.
        depth: float64 [G, R] that voxel's exit distance in voxel units; -1 when the ray never
            entered the grid.
    """
    bits = np.ascontiguousarray(occupied_bits, dtype=np.uint8)
    if bits.ndim != 3:
        raise ValueError(f"occupied_bits must be [X, Y, Z], got shape {bits.shape}")
    if not 1 <= num_bits <= 8:
        raise ValueError(f"num_bits must be in 1..8, got {num_bits}")
    start = np.asarray(origins, dtype=np.float32).reshape(-1, 3).astype(np.float64)
    end = np.asarray(endpoints, dtype=np.float32).reshape(-1, 3).astype(np.float64)
    if start.shape != end.shape:
        raise ValueError(f"origins {start.shape} and endpoints {end.shape} differ")
    if not (np.isfinite(start).all() and np.isfinite(end).all()):
        raise ValueError("ray origins and endpoints must be finite")
    if np.abs(start).max(initial=0.0) > 2.0 ** 30:
        raise ValueError("ray origins must lie within 2**30 voxels of the grid")
    if (start == end).all(axis=1).any():
        raise ValueError("a ray's end point equals its origin (no direction)")

    R = start.shape[0]
    voxel_out = np.zeros((num_bits, R), dtype=np.int64)
    depth_out = np.full((num_bits, R), -1.0, dtype=np.float64)
    if R == 0:
        return voxel_out, depth_out

    ray = end - start
    # the norm in C's order: ((rx * rx) + (ry * ry)) + (rz * rz)
    length = np.sqrt(ray[:, 0] * ray[:, 0] + ray[:, 1] * ray[:, 1] + ray[:, 2] * ray[:, 2])
    d = ray / length[:, None]
    step = np.where(d >= 0, 1, -1).astype(np.int64)
    v = np.trunc(start).astype(np.int64)                    # C int(): towards zero
    moving = d != 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t_max = np.where(moving, ((v + (step > 0)) - start) / d, DBL_MAX)
        t_delta = np.where(moving, step / d, DBL_MAX)

    # Most rays start inside the grid (every LiDAR origin does); they take the faster loop.
    start_inside = ((v >= 0) & (v < np.asarray(bits.shape))).all(axis=1)
    for subset, march in ((start_inside, _march_from_inside), (~start_inside, _march_general)):
        sel = np.flatnonzero(subset)
        if sel.size:
            voxel_out[:, sel], depth_out[:, sel] = march(
                bits, num_bits, v[sel], step[sel], t_max[sel], t_delta[sel], moving[sel])
    return voxel_out, depth_out


def _march_from_inside(bits, num_bits, v, step, t_max, t_delta, moving):
    """Rays whose start voxel lies inside the grid: the same loop as ``_march_general``, on
    a copy of the grid with a one-voxel border marked OUTSIDE, so a ray carries one flat index
    and learns it left the grid from the voxel it reads.

    Long because it is one vectorised loop that must take the reference kernel's steps in its
    order (tie-breaking, ``tMax += tDelta``); split, its float32 steps could no longer be read
    against the reference side by side."""
    R = v.shape[0]
    voxel_out = np.zeros((num_bits, R), dtype=np.int64)
    depth_out = np.full((num_bits, R), -1.0, dtype=np.float64)
    X, Y, Z = bits.shape
    padded = np.full((X + 2, Y + 2, Z + 2), OUTSIDE, dtype=np.uint16)
    padded[1:-1, 1:-1, 1:-1] = bits
    # one more cell after the grid: a finished ray is parked there (reads 0, does not move)
    flat = np.append(padded.ravel(), np.uint16(0))
    park = flat.size - 1
    strides = np.array([(Y + 2) * (Z + 2), Z + 2, 1], dtype=np.int64)
    rays = np.arange(R)
    index = (v + 1) @ strides
    jx, jy, jz = (step[:, a] * strides[a] for a in range(3))
    tx, ty, tz = (t_max[:, a].copy() for a in range(3))
    dx, dy, dz = (t_delta[:, a].copy() for a in range(3))
    pending = np.full(R, (1 << num_bits) - 1, dtype=np.uint16)   # layers not hit yet
    parked = np.uint16(1 << 15)      # pending value of a parked ray: never 0, matches nothing
    prev_index, prev_exit = index, np.full(R, -1.0)
    voxel_out[:] = park              # padded flat indices until the end

    def finish(done, index, exit_t):
        """Rays ``done`` (indices) end: layers not hit report voxel ``index``, depth
        ``exit_t``; the rays are parked."""
        open_layers = pending[done]
        for g in range(num_bits):
            m = (open_layers >> g) & 1 == 1
            voxel_out[g, rays[done[m]]] = index[m]
            depth_out[g, rays[done[m]]] = exit_t[m]
        park_rays(done)

    def park_rays(done):
        pending[done] = parked
        jx[done] = jy[done] = jz[done] = 0
        next_index[done] = park

    parked_count = 0
    with np.errstate(over="ignore"):  # DBL_MAX + DBL_MAX on an axis that is never stepped
        for iteration in range(MAX_STEP + 1):
            code = flat.take(index)
            # one axis per iteration: x if tx < ty and tx < tz; else y if ty < tz; else z,
            # i.e. z when tz <= min(tx, ty), else y when ty <= tx, else x
            nearest_xy = np.minimum(tx, ty)
            take_z = tz <= nearest_xy
            exit_t = np.minimum(nearest_xy, tz)
            take_y = ty <= tx
            take_y &= ~take_z
            take_x = ~(take_y | take_z)
            jump = np.where(take_x, jx, np.where(take_y, jy, jz))
            next_index = index + jump
            new = code & pending
            if new.any():
                hits = np.flatnonzero(new)
                for g in range(num_bits):
                    first = hits[(new[hits] >> g) & 1 == 1]
                    voxel_out[g, rays[first]] = index[first]
                    depth_out[g, rays[first]] = exit_t[first]
                pending[hits] ^= new[hits]
                complete = hits[pending[hits] == 0]
                if complete.size:
                    park_rays(complete)
                    parked_count += complete.size
            # a ray that reads the border had been inside: it ended in the previous voxel
            left = np.flatnonzero(code == OUTSIDE)
            if left.size:
                finish(left, prev_index[left], prev_exit[left])
                parked_count += left.size
            if iteration == MAX_STEP:
                live = np.flatnonzero(pending != parked)
                finish(live, index[live], exit_t[live])
                break
            if parked_count == R:
                break
            if parked_count * 8 >= rays.size:  # many finished: drop them from every column
                keep = pending != parked
                rays, index, next_index = rays[keep], index[keep], next_index[keep]
                jx, jy, jz = jx[keep], jy[keep], jz[keep]
                tx, ty, tz, dx, dy, dz = (a[keep] for a in (tx, ty, tz, dx, dy, dz))
                pending, exit_t = pending[keep], exit_t[keep]
                take_x, take_y, take_z = take_x[keep], take_y[keep], take_z[keep]
                R, parked_count = rays.size, 0
            prev_index, prev_exit, index = index, exit_t, next_index
            np.add(tx, dx, out=tx, where=take_x)
            np.add(ty, dy, out=ty, where=take_y)
            np.add(tz, dz, out=tz, where=take_z)
    # padded flat index -> grid flat index
    p = np.unravel_index(voxel_out, padded.shape)
    return ((p[0] - 1) * Y + (p[1] - 1)) * Z + (p[2] - 1), depth_out


def _march_general(bits, num_bits, v, step, t_max, t_delta, moving):
    """Any start voxel, inside the grid or not: the loop of the module docstring, with the
    grid bounds tested per axis. Long for the reason ``_march_from_inside`` gives."""
    R = v.shape[0]
    voxel_out = np.zeros((num_bits, R), dtype=np.int64)
    depth_out = np.full((num_bits, R), -1.0, dtype=np.float64)
    rays = np.arange(R)
    vx, vy, vz = (v[:, a].copy() for a in range(3))
    sx, sy, sz = (step[:, a].copy() for a in range(3))
    tx, ty, tz = (t_max[:, a].copy() for a in range(3))
    dx, dy, dz = (t_delta[:, a].copy() for a in range(3))
    # Outside the grid on an axis it never moves back along, a ray can never enter it.
    lx, ly, lz = ((step[:, a] < 0) | ~moving[:, a] for a in range(3))
    hx, hy, hz = ((step[:, a] > 0) | ~moving[:, a] for a in range(3))
    was_inside = np.zeros(R, dtype=bool)
    prev_index = np.zeros(R, dtype=np.int64)   # the voxel and exit distance of the previous
    prev_exit = np.full(R, -1.0)               # iteration: where a ray that left the grid was
    found = np.zeros(R, dtype=np.uint8)
    alive = np.ones(R, dtype=bool)   # finished rays stay in the columns until many have
    all_found = np.uint8((1 << num_bits) - 1)
    flat = bits.ravel()
    X, Y, Z = bits.shape
    maybe_outside = True             # some live ray has not been inside the grid yet

    def finish(done, inside, index, exit_t):
        """Rays ``done`` end: layers without a hit report the last voxel visited inside the
        grid (this iteration's if the ray is inside, else the previous one's) or none."""
        idx, entered, now = rays[done], was_inside[done], inside[done]
        voxel = np.where(now, index[done], prev_index[done])
        depth = np.where(now, exit_t[done], prev_exit[done])
        voxel[~entered], depth[~entered] = 0, -1.0
        for g in range(num_bits):
            open_ = (found[done] >> g) & 1 == 0
            voxel_out[g, idx[open_]] = voxel[open_]
            depth_out[g, idx[open_]] = depth[open_]

    with np.errstate(over="ignore"):  # DBL_MAX + DBL_MAX on an axis that is never stepped
        for iteration in range(MAX_STEP + 1):
            # unsigned views: a negative index is a huge one, so one comparison per axis
            inside = ((vx.view(np.uint64) < X) & (vy.view(np.uint64) < Y)
                      & (vz.view(np.uint64) < Z))
            done = was_inside & ~inside          # left the grid: the ray ends
            if maybe_outside:
                done |= ~was_inside & ~inside & (
                    ((vx < 0) & lx) | ((vx >= X) & hx) | ((vy < 0) & ly) | ((vy >= Y) & hy)
                    | ((vz < 0) & lz) | ((vz >= Z) & hz))
            # one axis per iteration: x if tx < ty and tx < tz; else y if ty < tz; else z.
            # The distance the chosen axis is crossed at is the smallest of the three.
            x_first = tx < ty
            take_x = x_first & (tx < tz)
            take_y = ~x_first & (ty < tz)
            take_z = ~(take_x | take_y)
            exit_t = np.minimum(np.minimum(tx, ty), tz)
            index = (vx * Y + vy) * Z + vz
            new = np.where(inside & alive, flat.take(index, mode="clip"), 0).astype(np.uint8)
            new &= ~found
            if new.any():
                for g in range(num_bits):
                    first = (new >> g) & 1 == 1
                    if first.any():
                        voxel_out[g, rays[first]] = index[first]
                        depth_out[g, rays[first]] = exit_t[first]
                found |= new
            was_inside |= inside
            done |= found == all_found
            if iteration == MAX_STEP:
                done[:] = True
            done &= alive
            if done.any():
                finish(done, inside, index, exit_t)
                alive &= ~done
                if not alive.any():
                    break
                if (~alive).sum() * 8 >= alive.size:  # many finished: drop them everywhere
                    keep = alive
                    rays, vx, vy, vz, sx, sy, sz = (
                        a[keep] for a in (rays, vx, vy, vz, sx, sy, sz))
                    tx, ty, tz, dx, dy, dz = (a[keep] for a in (tx, ty, tz, dx, dy, dz))
                    lx, ly, lz, hx, hy, hz = (a[keep] for a in (lx, ly, lz, hx, hy, hz))
                    was_inside, found, alive = (a[keep] for a in (was_inside, found, alive))
                    take_x, take_y, take_z = (a[keep] for a in (take_x, take_y, take_z))
                    index, exit_t = index[keep], exit_t[keep]
                    maybe_outside = not was_inside.all()
            prev_index, prev_exit = index, exit_t
            np.add(vx, sx, out=vx, where=take_x)
            np.add(vy, sy, out=vy, where=take_y)
            np.add(vz, sz, out=vz, where=take_z)
            np.add(tx, dx, out=tx, where=take_x)
            np.add(ty, dy, out=ty, where=take_y)
            np.add(tz, dz, out=tz, where=take_z)
    return voxel_out, depth_out
