"""Vectorised ray casting of rays sharing one origin (a camera or the LiDAR) against the
world's primitives and the ground plane z = 0.

Cost control: a sensor's rays form a 2D grid (image pixels, LiDAR beams x azimuths). For
every primitive the sensor computes a conservative rectangle of grid cells its bounding box
can cover; only those (ray, primitive) pairs are tested, in one batched pass per primitive
kind. The nearest hit per ray wins (a z-buffer).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .primitives import BOX, ELLIPSOID, FRUSTUM, Primitives

SKY = -1
GROUND = -2
EPS = 1e-6


@dataclass
class Hits:
    """Nearest hit per ray. N rays."""
    t: np.ndarray       # float64 [N] distance along the unit ray (inf: sky); float32-exact for objects
    prim: np.ndarray    # int32 [N] primitive index, GROUND or SKY
    normal: np.ndarray  # float32 [N, 3] unit world normal (0 for sky)
    local: np.ndarray   # float32 [N, 3] hit point in the primitive's local frame, metres
    pair_ray: np.ndarray   # int64 [Q] every (ray, primitive) pair that intersects, occluded or not
    pair_prim: np.ndarray  # int32 [Q]


def rect_pairs(r0, r1, c0, c1, width, wrap=False):
    """(ray, prim) index pairs for per-primitive cell rectangles [r0, r1) x [c0, c1).
    With ``wrap`` columns are taken modulo ``width`` (LiDAR azimuth)."""
    nr = np.maximum(r1 - r0, 0)
    nc = np.maximum(c1 - c0, 0)
    counts = nr * nc
    total = int(counts.sum())
    prim = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
    starts = np.cumsum(counts) - counts
    off = np.arange(total, dtype=np.int64) - np.repeat(starts, counts)
    q, rem = np.divmod(off, nc[prim])
    rows = r0[prim] + q
    cols = c0[prim] + rem
    if wrap:
        cols = cols % width
    return rows * width + cols, prim


def _intersect(prims: Primitives, origin, dirs, ray, prim, pair_origins=None):
    """Ray parameter of the first entry into primitive ``prim[q]`` along ray ``ray[q]``
    (inf when missed or when the origin is inside). float32 [Q], same order as the input.
    Rays start at ``origin`` [3], or at ``pair_origins`` [Q, 3] (one per pair) when given."""
    t = np.full(len(ray), np.inf, np.float32)
    if len(ray) == 0:
        return t
    cp, sp = np.cos(prims.yaw), np.sin(prims.yaw)
    inv_half = (1.0 / prims.half).astype(np.float32)
    if pair_origins is None:
        # the shared origin in every primitive's unit frame, then gathered per pair
        oc = origin[None, :] - prims.center
        o_p = (np.stack([cp * oc[:, 0] + sp * oc[:, 1], -sp * oc[:, 0] + cp * oc[:, 1], oc[:, 2]], -1)
               * inv_half).astype(np.float32)
        o_all = o_p[prim]
    else:
        oc = pair_origins - prims.center[prim]
        c, s = cp[prim], sp[prim]
        o_all = (np.stack([c * oc[:, 0] + s * oc[:, 1], -s * oc[:, 0] + c * oc[:, 1], oc[:, 2]], -1)
                 * inv_half[prim]).astype(np.float32)
    cp, sp = cp.astype(np.float32), sp.astype(np.float32)
    dirs32 = dirs.astype(np.float32)
    kind = prims.kind[prim]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for k in (BOX, ELLIPSOID, FRUSTUM):
            sel = np.flatnonzero(kind == k)
            if not len(sel):
                continue
            p, r = prim[sel], ray[sel]
            c, s = cp[p], sp[p]
            dw = dirs32[r]
            ih = inv_half[p]
            d0 = (c * dw[:, 0] + s * dw[:, 1]) * ih[:, 0]
            d1 = (c * dw[:, 1] - s * dw[:, 0]) * ih[:, 1]
            d2 = dw[:, 2] * ih[:, 2]
            o = o_all[sel]
            o0, o1, o2 = o[:, 0], o[:, 1], o[:, 2]
            if k == BOX:
                tn = np.full(len(sel), -np.inf, np.float32)
                tf = np.full(len(sel), np.inf, np.float32)
                for oo, dd in ((o0, d0), (o1, d1), (o2, d2)):
                    inv = 1.0 / dd
                    ta = (-1.0 - oo) * inv
                    tb = (1.0 - oo) * inv
                    np.maximum(tn, np.minimum(ta, tb), out=tn)
                    np.minimum(tf, np.maximum(ta, tb), out=tf)
                t[sel] = np.where((tn <= tf) & (tn > EPS), tn, np.inf)
            elif k == ELLIPSOID:
                a = d0 * d0 + d1 * d1 + d2 * d2
                b = o0 * d0 + o1 * d1 + o2 * d2
                cc = o0 * o0 + o1 * o1 + o2 * o2 - 1.0
                disc = b * b - a * cc
                tt = (-b - np.sqrt(np.maximum(disc, 0))) / a
                t[sel] = np.where((disc >= 0) & (tt > EPS) & (cc > 0), tt, np.inf)
            else:
                tau = prims.taper[p].astype(np.float32)
                k0, k1 = (1 + tau) / 2, (tau - 1) / 2
                mz = k0 + k1 * o2
                A = d0 * d0 + d1 * d1 - k1 * k1 * d2 * d2
                B = o0 * d0 + o1 * d1 - k1 * d2 * mz
                C = o0 * o0 + o1 * o1 - mz * mz
                disc = B * B - A * C
                sq = np.sqrt(np.maximum(disc, 0))
                small = np.abs(A) < 1e-9
                best = np.full(len(A), np.inf, np.float32)
                for root in ((-B - sq) / A, (-B + sq) / A, np.where(small, -C / (2 * B), np.inf)):
                    z = o2 + root * d2
                    ok = (root > EPS) & (np.abs(z) <= 1.0) & np.isfinite(root) & ((disc >= 0) | small)
                    best = np.where(ok & (root < best), root, best)
                for zc, rc in ((-1.0, np.ones_like(tau)), (1.0, tau)):
                    root = (zc - o2) / d2
                    px = o0 + root * d0
                    py = o1 + root * d1
                    ok = (root > EPS) & (px * px + py * py <= rc * rc) & np.isfinite(root)
                    best = np.where(ok & (root < best), root, best)
                # the origin must be outside (inside only happens for degenerate placements)
                inside = (np.abs(o2) <= 1) & (o0 * o0 + o1 * o1 < mz * mz)
                t[sel] = np.where(inside, np.inf, best)
    return t


def surface(prims: Primitives, index, points_global):
    """Unit world normals [Q, 3] and local hit coordinates [Q, 3] (metres) at surface points
    of primitives ``index[q]``."""
    u = prims.to_unit(points_global, index).astype(np.float32)
    kind = prims.kind[index]
    n = np.zeros_like(u)
    box = kind == BOX
    if box.any():
        ub = u[box]
        axis = np.argmax(np.abs(ub), 1)
        nb = np.zeros_like(ub)
        nb[np.arange(len(ub)), axis] = np.sign(ub[np.arange(len(ub)), axis])
        n[box] = nb
    ell = kind == ELLIPSOID
    n[ell] = u[ell]
    fru = kind == FRUSTUM
    if fru.any():
        uf = u[fru]
        tau = prims.taper[index][fru]
        k0, k1 = (1 + tau) / 2, (tau - 1) / 2
        r = k0 + k1 * uf[:, 2]
        nf = np.stack([uf[:, 0], uf[:, 1], -k1 * r], -1)
        cap = np.abs(uf[:, 2]) > 1 - 1e-6
        radial2 = uf[:, 0] ** 2 + uf[:, 1] ** 2
        cap &= radial2 < (r * r) * (1 - 1e-6)
        nf[cap] = np.stack([np.zeros(cap.sum()), np.zeros(cap.sum()), np.sign(uf[cap, 2])], -1)
        n[fru] = nf
    half = prims.half[index].astype(np.float32)
    n = n / half
    c, s = np.cos(prims.yaw[index]).astype(np.float32), np.sin(prims.yaw[index]).astype(np.float32)
    nw = np.stack([c * n[:, 0] - s * n[:, 1], s * n[:, 0] + c * n[:, 1], n[:, 2]], -1)
    nw /= np.maximum(np.linalg.norm(nw, axis=1, keepdims=True), 1e-12)
    return nw.astype(np.float32), (u * half).astype(np.float32)


def cast(prims: Primitives, origin, dirs, pair_ray, pair_prim, max_t=np.inf) -> Hits:
    """Nearest hit of rays ``origin + t * dirs[n]`` (dirs unit, [N, 3], global) among the
    candidate pairs and the ground plane z = 0 (hit from above only)."""
    origin = np.asarray(origin, dtype=np.float64)
    n = len(dirs)
    t_pair = _intersect(prims, origin, dirs, pair_ray, pair_prim)
    hit = t_pair < max_t
    pr, pp, tp = pair_ray[hit], pair_prim[hit], t_pair[hit]
    tbuf = np.full(n, np.inf, np.float32)   # same dtype as tp: ufunc.at is slow when casting
    np.minimum.at(tbuf, pr, tp)
    prim = np.full(n, SKY, np.int32)
    win = tp == tbuf[pr]
    prim[pr[win]] = pp[win]
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(dirs[:, 2] < -1e-9, -origin[2] / dirs[:, 2], np.inf)
    ground = (tg < tbuf) & (tg < max_t) & (origin[2] > 0)
    tbuf = tbuf.astype(np.float64)
    tbuf[ground] = tg[ground]
    prim[ground] = GROUND
    normal = np.zeros((n, 3), np.float32)
    local = np.zeros((n, 3), np.float32)
    normal[ground, 2] = 1.0
    obj = np.flatnonzero(prim >= 0)
    if len(obj):
        pts = origin[None] + tbuf[obj, None] * dirs[obj]
        normal[obj], local[obj] = surface(prims, prim[obj], pts)
    return Hits(tbuf, prim, normal, local, pr, pp)


def shadowed(prims: Primitives, points, normals, sun, cell=2.0) -> np.ndarray:
    """Whether surface points [M, 3] (global, with unit normals [M, 3]) are in the shadow of any
    primitive for the directional light towards unit ``sun``. bool [M].

    Candidates: a primitive can only shade points whose xy lies in the xy bounding box of the
    primitive swept along -sun down to the ground. Points are binned into ``cell``-metre
    cells; a (primitive, cell) overlap test picks the pairs to intersect."""
    m = len(points)
    out = np.zeros(m, bool)
    if m == 0 or len(prims) == 0 or sun[2] <= 0.02:
        return out
    origins = points + 0.03 * normals
    corners = prims.corners()                                             # [P, 8, 3]
    drop = corners[..., :2] - (np.maximum(corners[..., 2:3], 0) / sun[2]) * sun[None, None, :2]
    allxy = np.concatenate([corners[..., :2], drop], 1)
    lo, hi = allxy.min(1), allxy.max(1)                                   # [P, 2]
    keep = np.all((lo <= origins[:, :2].max(0)) & (hi >= origins[:, :2].min(0)), axis=1)
    keep_idx = np.flatnonzero(keep)
    lo, hi = lo[keep_idx], hi[keep_idx]
    key_xy = np.floor(origins[:, :2] / cell).astype(np.int64)
    key = key_xy[:, 0] * 1_000_003 + key_xy[:, 1]
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    cells, start = np.unique(key_sorted, return_index=True)
    end = np.append(start[1:], m)
    cxy = key_xy[order[start]]                                            # [U, 2] cell indices
    c_lo, c_hi = cxy * cell, (cxy + 1) * cell
    over = ((lo[:, None, 0] <= c_hi[None, :, 0]) & (hi[:, None, 0] >= c_lo[None, :, 0])
            & (lo[:, None, 1] <= c_hi[None, :, 1]) & (hi[:, None, 1] >= c_lo[None, :, 1]))
    pp, cc = np.nonzero(over)                                             # (primitive, cell) pairs
    pp = keep_idx[pp]
    counts = end[cc] - start[cc]
    prim = np.repeat(pp, counts).astype(np.int32)
    first = np.repeat(start[cc] - (np.cumsum(counts) - counts), counts)
    recv = order[np.arange(counts.sum()) + first]
    dirs = np.broadcast_to(np.asarray(sun, float), (1, 3))
    t = _intersect(prims, None, dirs, np.zeros(len(recv), np.int64), prim, pair_origins=origins[recv])
    out[recv[np.isfinite(t)]] = True
    return out
