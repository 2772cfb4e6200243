"""Camera images from ray-cast hits: procedural textures per material, Lambert + specular
shading with the scene's sun and sky light, sky gradient with clouds, aerial perspective,
and a sensor model (exposure, vignetting, shot/read noise). All deterministic.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import materials as M
from .primitives import Primitives
from .scene_raycast import GROUND, SKY, Hits, shadowed
from .world import WHITE, YELLOW, World


# -- deterministic value noise -----------------------------------------------------------------

def _hash(ix, iy, iz, seed):
    """Integer lattice -> float32 in [0, 1) (splitmix-style mixing, wraps on overflow)."""
    h = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) ^ (iz.astype(np.int64) * 83492791)
    h = h ^ np.int64(seed * 2654435761 % (1 << 31))
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return ((h & 0xFFFFFF).astype(np.float32)) / np.float32(1 << 24)


def hash_cell(x, y, z, seed):
    """Random value in [0, 1) per integer cell of (x, y, z) (floats, floored)."""
    return _hash(np.floor(x), np.floor(y), np.floor(z), seed)


def _make_tile(size=256, cell=8):
    """Periodic smooth value noise on a size x size texel tile, lattice every ``cell`` texels."""
    n = size // cell
    lattice = _hash(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), np.zeros((n, n), np.int64), 12345)
    t = (np.arange(size) % cell) / cell
    t = t * t * (3 - 2 * t)
    i0 = np.arange(size) // cell
    i1 = (i0 + 1) % n
    rows = lattice[i0] * (1 - t)[:, None] + lattice[i1] * t[:, None]          # along x
    tile = rows[:, i0] * (1 - t)[None, :] + rows[:, i1] * t[None, :]          # along y
    return np.ascontiguousarray(tile, dtype=np.float32).ravel()


_TILE_SIZE, _TILE_CELL = 256, 8
_TILE = _make_tile(_TILE_SIZE, _TILE_CELL)


def value_noise2(x, y, seed):
    """Smooth 2D value noise in [0, 1), unit feature size (a bilinear lookup of a periodic tile,
    shifted per seed; the tile repeats every 32 units)."""
    off = (seed * 2654435761) % (1 << 20)
    u = np.asarray(x, np.float32) * _TILE_CELL + np.float32(off % 251)
    v = np.asarray(y, np.float32) * _TILE_CELL + np.float32((off // 251) % 241)
    fu, fv = np.floor(u), np.floor(v)
    tu, tv = u - fu, v - fv
    iu = fu.astype(np.int64) & (_TILE_SIZE - 1)
    iv = fv.astype(np.int64) & (_TILE_SIZE - 1)
    iu1, iv1 = (iu + 1) & (_TILE_SIZE - 1), (iv + 1) & (_TILE_SIZE - 1)
    iu, iu1 = iu * _TILE_SIZE, iu1 * _TILE_SIZE
    a = _TILE[iu + iv] * (1 - tv) + _TILE[iu + iv1] * tv
    b = _TILE[iu1 + iv] * (1 - tv) + _TILE[iu1 + iv1] * tv
    return a * (1 - tu) + b * tu


def value_noise(x, y, z, seed):
    """3D-looking noise from the 2D tile on a skewed projection (cheap, good enough for texture)."""
    return value_noise2(x + 0.57 * z, y - 0.71 * z, seed)


def fbm2(x, y, scale, octaves, seed):
    """Fractal 2D noise in about [-0.5, 0.5], features of size ``scale`` metres and finer."""
    out, amp, total = 0.0, 1.0, 0.0
    for o in range(octaves):
        f = (2.0 ** o) / scale
        out = out + amp * (value_noise2(x * f, y * f, seed + 17 * o) - 0.5)
        total += amp
        amp *= 0.5
    return out / total


def _frac(x):
    return x - np.floor(x)


# -- materials -----------------------------------------------------------------------------------

def _ground_albedo(mat, paint, x, y, seed):
    """Albedo [n, 3] of ground points (city-frame metres x, y)."""
    n = len(mat)
    alb = np.zeros((n, 3), np.float32)
    coarse = fbm2(x, y, 6.0, 2, seed + 1)
    fine = value_noise2(x * 9.0, y * 9.0, seed + 2) - 0.5

    def put(m, base, var_coarse, var_fine):
        sel = mat == m
        if sel.any():
            k = 1 + var_coarse * coarse[sel] + var_fine * fine[sel]
            alb[sel] = np.asarray(base, np.float32)[None] * k[:, None]
        return sel

    put(M.ASPHALT, (0.3, 0.3, 0.31), 0.35, 0.25)
    sel = put(M.PARKING, (0.36, 0.35, 0.34), 0.3, 0.25)
    if sel.any():  # stall lines
        line = _frac(x[sel] / 2.7) < 0.05
        alb[np.flatnonzero(sel)[line]] = 0.75
    sel = put(M.TILES, (0.58, 0.56, 0.53), 0.2, 0.08)
    if sel.any():
        xs, ys = x[sel], y[sel]
        tile = 0.85 + 0.3 * hash_cell(xs / 0.5, ys / 0.5, 0, seed + 3)
        grout = (_frac(xs / 0.5) < 0.06) | (_frac(ys / 0.5) < 0.06)
        alb[sel] *= np.where(grout, 0.6, tile)[:, None]
    sel = put(M.COBBLE, (0.48, 0.34, 0.28), 0.2, 0.1)
    if sel.any():
        xs, ys = x[sel], y[sel]
        row = np.floor(ys / 0.22)
        xo = xs / 0.3 + 0.5 * (row % 2)
        stone = 0.75 + 0.5 * hash_cell(xo, row, 1, seed + 4)
        gap = (_frac(xo) < 0.1) | (_frac(ys / 0.22) < 0.12)
        alb[sel] *= np.where(gap, 0.45, stone)[:, None]
    sel = put(M.GRASS, (0.22, 0.38, 0.12), 0.5, 0.45)
    if sel.any():
        hue = value_noise2(x[sel] / 3.0, y[sel] / 3.0, seed + 5)[:, None]
        alb[sel] = alb[sel] * (1 - 0.35 * hue) + 0.35 * hue * np.array([0.38, 0.36, 0.18], np.float32)
    put(M.DIRT, (0.42, 0.33, 0.22), 0.4, 0.4)
    sel = put(M.GRAVEL, (0.5, 0.48, 0.44), 0.15, 0.2)
    if sel.any():
        alb[sel] *= (0.7 + 0.6 * hash_cell(x[sel] / 0.05, y[sel] / 0.05, 2, seed + 6))[:, None]
    wear = 0.85 + 0.3 * (value_noise2(x * 3, y * 3, seed + 7))
    white = paint == WHITE
    alb[white] = (np.array([0.82, 0.82, 0.8], np.float32)[None] * wear[white, None])
    yellow = paint == YELLOW
    alb[yellow] = (np.array([0.85, 0.68, 0.15], np.float32)[None] * wear[yellow, None])
    return alb


@dataclass
class _ObjectHits:
    """Hits on object primitives in their local frames, and what the material textures share."""
    lx: np.ndarray       # local coordinates (metres) [n]
    ly: np.ndarray
    lz: np.ndarray
    n_local: np.ndarray  # local normals [n, 3]
    half: np.ndarray     # the primitives' half extents [n, 3]
    base: np.ndarray     # the primitives' base albedo [n, 3]
    zb: np.ndarray       # height above the primitive's bottom
    pid: np.ndarray      # per-primitive random number in [0, 1)
    side_x: np.ndarray   # face normal along local x
    top: np.ndarray      # face normal up
    along: np.ndarray    # horizontal coordinate on a vertical face
    dirt: np.ndarray     # grime noise in about [-0.5, 0.5]
    seed: int


def _object_albedo(prims: Primitives, idx, local, n_local, seed):
    """Albedo [n, 3] of hits on primitives ``idx`` at local points (metres) with local normals:
    the base colour, textured per material (``_TEXTURES``)."""
    mat = prims.material[idx]
    base = prims.color[idx].astype(np.float32)
    half = prims.half[idx].astype(np.float32)
    alb = base.copy()
    lx, ly, lz = local[:, 0], local[:, 1], local[:, 2]
    zb = lz + half[:, 2]   # height above the primitive's bottom
    # per-primitive random numbers (stable: hashed from its rounded centre)
    pid = hash_cell(prims.center[idx, 0] * 10, prims.center[idx, 1] * 10, prims.center[idx, 2] * 10, seed)
    side_x = np.abs(n_local[:, 0]) > 0.5          # face normal along local x
    top = n_local[:, 2] > 0.5
    along = np.where(side_x, ly, lx)              # horizontal coordinate on a vertical face
    dirt = fbm2(lx + 3 * ly, lz + ly, 1.5, 2, seed + 11)
    hits = _ObjectHits(lx, ly, lz, n_local, half, base, zb, pid, side_x, top, along, dirt, seed)
    for material, texture in _TEXTURES.items():
        i = np.flatnonzero(mat == material)
        if len(i):
            texture(alb, i, hits)
    return np.clip(alb, 0, 1)


# Material textures: each rewrites alb[i], the albedo of its hits i (indices into ``hits``).

def _facade_texture(alb, i, hits: _ObjectHits):
    """Windows on every floor (panes of varying brightness), shop windows at street level,
    grime; a grey roof."""
    lx, ly, zb, pid, along, top, dirt, seed = (hits.lx, hits.ly, hits.zb, hits.pid, hits.along, hits.top,
                                               hits.dirt, hits.seed)
    floor_h = 3.0 + 0.6 * pid[i]
    spacing = 2.4 + 1.8 * _frac(pid[i] * 7.3)
    wx = _frac(along[i] / spacing)
    wz = _frac((zb[i] - 0.3) / floor_h)
    width = 0.35 + 0.3 * _frac(pid[i] * 13.1)
    window = (np.abs(wx - 0.5) < width / 2) & (wz > 0.3) & (wz < 0.8) & (zb[i] > 1.0) & ~top[i]
    shop = (zb[i] < 2.8) & (zb[i] > 0.3) & (np.abs(wx - 0.5) < 0.42) & (_frac(pid[i] * 3.7) < 0.5) & ~top[i]
    lit = hash_cell(along[i] / spacing, zb[i] / floor_h, pid[i] * 1000, seed + 12)
    glass = np.stack([0.12 + 0.1 * lit, 0.15 + 0.1 * lit, 0.2 + 0.12 * lit], -1).astype(np.float32)
    a = alb[i] * (1 + 0.25 * dirt[i])[:, None]
    a = np.where((window | shop)[:, None], glass, a)
    roof_grain = 0.8 + 0.4 * value_noise2(lx[i], ly[i], seed + 13)
    roof = np.array([0.32, 0.31, 0.3], np.float32)[None] * roof_grain[:, None]
    alb[i] = np.where(top[i][:, None], roof, a)


def _foliage_texture(alb, i, hits: _ObjectHits):
    """Leaves and clumps."""
    lx, ly, lz, seed = hits.lx, hits.ly, hits.lz, hits.seed
    leaf = value_noise(lx[i] * 4, ly[i] * 4, lz[i] * 4, seed + 14)
    clump = value_noise(lx[i] * 0.8, ly[i] * 0.8, lz[i] * 0.8, seed + 15)
    alb[i] *= (0.45 + 0.55 * leaf * 0.7 + 0.5 * clump * 0.6)[:, None]


def _bark_texture(alb, i, hits: _ObjectHits):
    """Vertical streaks around the trunk."""
    lx, ly, zb, seed = hits.lx, hits.ly, hits.zb, hits.seed
    ang = np.arctan2(ly[i], lx[i])
    alb[i] *= (0.6 + 0.6 * value_noise2(ang * 6, zb[i] * 0.7, seed + 16))[:, None]


def _sign_texture(alb, i, hits: _ObjectHits):
    """A light border on the face, a grey back."""
    ly, lz, half, n_local = hits.ly, hits.lz, hits.half, hits.n_local
    border = (np.abs(ly[i]) > 0.82 * half[i, 1]) | (np.abs(lz[i]) > 0.82 * half[i, 2])
    back = n_local[i, 0] < 0
    alb[i] = np.where(border[:, None], 0.9, alb[i])
    alb[i] = np.where(back[:, None], 0.5, alb[i])


def _paint_texture(alb, i, hits: _ObjectHits):
    """Car body: dark sills, head and tail lights at the upper corners, a dark grille."""
    ly, zb, half, n_local = hits.ly, hits.zb, hits.half, hits.n_local
    sill = (zb[i] < 0.12 * 2 * half[i, 2])
    alb[i] *= np.where(sill, 0.45, 1.0)[:, None]
    front = n_local[i, 0] > 0.7
    rear = n_local[i, 0] < -0.7
    upper = zb[i] > 1.0 * half[i, 2]
    corner = np.abs(ly[i]) > 0.62 * half[i, 1]
    grille = front & ~corner & ~upper
    alb[i] = np.where((front & corner & upper)[:, None], np.array([0.95, 0.95, 0.9], np.float32), alb[i])
    alb[i] = np.where((rear & corner & upper)[:, None], np.array([0.7, 0.05, 0.05], np.float32), alb[i])
    alb[i] = np.where(grille[:, None], alb[i] * 0.35, alb[i])


def _glass_texture(alb, i, hits: _ObjectHits):
    """Dark panes, lighter towards the top, between pillars in the base colour; base-coloured top."""
    along, side_x, half, zb, base, top = hits.along, hits.side_x, hits.half, hits.zb, hits.base, hits.top
    pillar = (np.abs(along[i]) > np.where(side_x[i], half[i, 1], half[i, 0]) - 0.12) | \
             (np.abs(_frac(along[i] / 1.3) - 0.5) < 0.04)
    pane = np.array([0.07, 0.08, 0.1], np.float32)[None] * (1 + 0.6 * zb[i, None] / (2 * half[i, 2:3]))
    a = np.where(pillar[:, None], base[i], pane)
    alb[i] = np.where(top[i][:, None], base[i], a)


def _tyre_texture(alb, i, hits: _ObjectHits):
    """A grey rim on the wheel's sides."""
    lx, lz, half, n_local = hits.lx, hits.lz, hits.half, hits.n_local
    rim = (np.abs(n_local[i, 1]) > 0.85) & (lx[i] ** 2 + (lz[i]) ** 2 < (0.55 * half[i, 0]) ** 2)
    alb[i] = np.where(rim[:, None], np.array([0.45, 0.45, 0.47], np.float32), alb[i])


def _cloth_texture(alb, i, hits: _ObjectHits):
    """Fine folds."""
    lx, ly, lz, seed = hits.lx, hits.ly, hits.lz, hits.seed
    alb[i] *= (0.75 + 0.5 * value_noise(lx[i] * 6, ly[i] * 6, lz[i] * 6, seed + 17))[:, None]


def _skin_texture(alb, i, hits: _ObjectHits):
    """Dark or light hair on the top and back of the head."""
    lx, lz, half, pid = hits.lx, hits.lz, hits.half, hits.pid
    hair = (lz[i] > 0.35 * half[i, 2]) | ((lx[i] < -0.2 * half[i, 0]) & (lz[i] > -0.2 * half[i, 2]))
    hair_color = np.where(_frac(pid[i] * 5.1) < 0.5, 0.08, 0.3)[:, None] * np.array([1.0, 0.8, 0.6], np.float32)
    alb[i] = np.where(hair[:, None], hair_color, alb[i])


def _concrete_texture(alb, i, hits: _ObjectHits):
    """Grime."""
    alb[i] *= (1 + 0.3 * hits.dirt[i])[:, None]


def _cone_texture(alb, i, hits: _ObjectHits):
    """Two white reflective bands."""
    zb, half = hits.zb, hits.half
    rel = zb[i] / (2 * half[i, 2])
    band = ((rel > 0.55) & (rel < 0.68)) | ((rel > 0.3) & (rel < 0.4))
    alb[i] = np.where(band[:, None], np.array([0.92, 0.92, 0.92], np.float32), alb[i])


def _plastic_texture(alb, i, hits: _ObjectHits):
    """A darker lid."""
    zb, half = hits.zb, hits.half
    lid = zb[i] > 2 * half[i, 2] - 0.08
    alb[i] *= np.where(lid, 0.6, 1.0)[:, None]


def _bus_body_texture(alb, i, hits: _ObjectHits):
    """A band of dark windows between frames, a darker stripe below it."""
    zb, half, along = hits.zb, hits.half, hits.along
    rel = zb[i] / (2 * half[i, 2])
    band = (rel > 0.45) & (rel < 0.86) & (np.abs(_frac(along[i] / 1.6) - 0.5) > 0.05)
    stripe = (rel > 0.3) & (rel < 0.36)
    a = np.where(band[:, None], np.array([0.08, 0.1, 0.12], np.float32), alb[i])
    alb[i] = np.where(stripe[:, None], a * 0.4, a)


def _cargo_texture(alb, i, hits: _ObjectHits):
    """Ribbed sides with grime."""
    along, dirt = hits.along, hits.dirt
    rib = _frac(along[i] / 0.6) < 0.1
    alb[i] *= np.where(rib, 0.75, 1.0)[:, None] * (1 + 0.2 * dirt[i])[:, None]


def _hazard_texture(alb, i, hits: _ObjectHits):
    """Black diagonal stripes along the bottom, grime."""
    along, zb, half, dirt = hits.along, hits.zb, hits.half, hits.dirt
    rel = zb[i] / (2 * half[i, 2])
    diag = (_frac((along[i] + zb[i]) / 0.5) < 0.5) & (rel < 0.3)
    dirty = alb[i] * (1 + 0.3 * dirt[i])[:, None]
    alb[i] = np.where(diag[:, None], np.array([0.08, 0.08, 0.08], np.float32), dirty)


def _stripes_texture(alb, i, hits: _ObjectHits):
    """White diagonal stripes."""
    along, zb = hits.along, hits.zb
    white = _frac((along[i] + zb[i]) / 0.7) < 0.5
    alb[i] = np.where(white[:, None], np.array([0.92, 0.92, 0.9], np.float32), alb[i])


def _fence_texture(alb, i, hits: _ObjectHits):
    """A wire mesh, darker between the wires."""
    along, zb = hits.along, hits.zb
    mesh = (_frac(along[i] / 0.12) < 0.3) | (_frac(zb[i] / 0.12) < 0.3)
    alb[i] *= np.where(mesh, 1.0, 0.55)[:, None]


def _metal_texture(alb, i, hits: _ObjectHits):
    """Slight mottling."""
    zb, along, seed = hits.zb, hits.along, hits.seed
    alb[i] *= (0.9 + 0.2 * value_noise2(zb[i] * 2, along[i] * 2, seed + 18))[:, None]


_TEXTURES = {
    M.FACADE: _facade_texture, M.FOLIAGE: _foliage_texture, M.BARK: _bark_texture, M.SIGN: _sign_texture,
    M.PAINT: _paint_texture, M.GLASS: _glass_texture, M.TYRE: _tyre_texture, M.CLOTH: _cloth_texture,
    M.SKIN: _skin_texture, M.CONCRETE: _concrete_texture, M.CONE: _cone_texture, M.PLASTIC: _plastic_texture,
    M.BUS_BODY: _bus_body_texture, M.CARGO: _cargo_texture, M.HAZARD: _hazard_texture,
    M.STRIPES: _stripes_texture, M.FENCE: _fence_texture, M.METAL: _metal_texture,
}   # M.LAMP keeps its base colour


SPECULAR = {M.PAINT: (0.5, 60.0), M.GLASS: (0.8, 120.0), M.METAL: (0.3, 30.0), M.BUS_BODY: (0.35, 60.0),
            M.SIGN: (0.2, 20.0), M.PLASTIC: (0.15, 20.0)}
_SPEC_KS = np.zeros(256, np.float32)
_SPEC_SH = np.full(256, 10.0, np.float32)
for _m, (_ks, _sh) in SPECULAR.items():
    _SPEC_KS[_m], _SPEC_SH[_m] = _ks, _sh


def sky_color(dirs, lighting, seed):
    """RGB [n, 3] of the sky along unit global directions."""
    up = np.clip(dirs[:, 2], 0, 1)[:, None]
    col = lighting.horizon[None] * (1 - np.sqrt(up)) + lighting.zenith[None] * np.sqrt(up)
    with np.errstate(divide="ignore", invalid="ignore"):
        px = dirs[:, 0] / np.maximum(dirs[:, 2], 0.03)
        py = dirs[:, 1] / np.maximum(dirs[:, 2], 0.03)
    cloud = fbm2(px.astype(np.float32), py.astype(np.float32), 1.3, 2, seed + 21) + 0.5
    cover = np.clip((cloud - (0.75 - 0.6 * lighting.cloudiness)) * 3, 0, 1)[:, None]
    col = col * (1 - cover) + cover * np.array([0.9, 0.9, 0.92]) * (0.75 + 0.25 * up)
    cos_sun = dirs @ lighting.sun
    near_sun = np.flatnonzero(cos_sun > 0.9)   # glow ** 64 < 0.001 elsewhere
    glow = cos_sun[near_sun, None]
    col[near_sun] += lighting.sun_color[None] * (glow ** 64 * 0.5 + glow ** 1500 * 3.0) * (1 - lighting.cloudiness)
    return col.astype(np.float32)


_VIGNETTE = {}


def _vignette(h, w):
    if (h, w) not in _VIGNETTE:
        v, u = np.meshgrid((np.arange(h) + 0.5) / h - 0.5, (np.arange(w) + 0.5) / w - 0.5, indexing="ij")
        _VIGNETTE[(h, w)] = (1 - 0.35 * (u * u + v * v)).astype(np.float32)
    return _VIGNETTE[(h, w)]


def shade(world: World, prims: Primitives, hits: Hits, origin, dirs, hw, seed, camera_gain=1.0):
    """uint8 [H, W, 3] image of one camera from its hits. ``seed`` makes the sensor noise."""
    L = world.lighting
    n = len(dirs)
    sky = hits.prim == SKY
    ground = hits.prim == GROUND
    tex_seed = world.texture_seed
    normal = hits.normal                      # float32, zero for sky
    d32 = dirs.astype(np.float32)
    albedo = np.zeros((n, 3), np.float32)
    specular = np.zeros(n, np.float32)
    shininess = np.full(n, 10.0, np.float32)
    gi = np.flatnonzero(ground)
    if len(gi):
        p = origin[None, :2] + hits.t[gi, None] * dirs[gi, :2]
        c = world.global_to_city_xy(p).astype(np.float32)
        mat, paint = world.ground.lookup(c[:, 0], c[:, 1])
        albedo[gi] = _ground_albedo(mat, paint, c[:, 0], c[:, 1], tex_seed)
        specular[gi] = 0.05
    oi = np.flatnonzero(hits.prim >= 0)
    if len(oi):
        pid = hits.prim[oi]
        # local normal = inverse yaw rotation of the world normal
        cy, sy = np.cos(prims.yaw[pid]).astype(np.float32), np.sin(prims.yaw[pid]).astype(np.float32)
        nw = normal[oi]
        n_local = np.stack([cy * nw[:, 0] + sy * nw[:, 1], -sy * nw[:, 0] + cy * nw[:, 1], nw[:, 2]], -1)
        albedo[oi] = _object_albedo(prims, pid, hits.local[oi], n_local, tex_seed)
        ks = _SPEC_KS[prims.material[pid]]
        specular[oi] = ks
        shininess[oi] = np.where(ks > 0, _SPEC_SH[prims.material[pid]], 10.0)
    sun = L.sun.astype(np.float32)
    sun_rgb = L.sun_color.astype(np.float32)[None]
    lam = np.clip(normal @ sun, 0, 1)
    # cast shadows: traced for one pixel of every 2 x 2 block (the cost of a shadow ray grows
    # with the pixel density), shared by the lit pixels of the block
    h, w = hw
    rep = (np.arange(h)[:, None] // 2 * 2 * w + np.arange(w)[None, :] // 2 * 2).ravel()
    probe = np.flatnonzero(lam[rep[np.unique(rep)]] > 0)
    probe = np.unique(rep)[probe]
    if len(probe):
        pts = origin[None] + hits.t[probe, None] * dirs[probe]
        dark = np.zeros(n, bool)
        dark[probe] = shadowed(prims, pts, normal[probe].astype(np.float64), L.sun)
        lam[dark[rep]] = 0.0
    amb = L.ambient.astype(np.float32)[None] * (0.55 + 0.45 * normal[:, 2:3])
    col = albedo * (amb + sun_rgb * lam[:, None])
    half_vec = sun[None] - d32
    half_vec /= np.linalg.norm(half_vec, axis=1, keepdims=True)
    spec = np.clip(np.einsum("ij,ij->i", normal, half_vec), 0, 1) ** shininess
    col += ((specular * spec) * (lam > 0))[:, None] * sun_rgb
    # reflections of the sky on shiny surfaces (Fresnel-ish)
    cos_v = np.abs(np.einsum("ij,ij->i", normal, d32))
    refl = (specular * (1 - cos_v) ** 3)[:, None]
    horizon = L.horizon.astype(np.float32)[None]
    col = col * (1 - refl) + refl * horizon
    t = np.where(sky, 0, hits.t).astype(np.float32)
    fog = np.exp(-t / np.float32(L.fog_distance))[:, None]
    color = col * fog + horizon * (1 - fog)
    color[sky] = sky_color(dirs[sky], L, tex_seed)
    # sensor: exposure, tone curve, vignetting, noise
    h, w = hw
    img = color.reshape(h, w, 3) * np.float32(L.exposure * camera_gain)
    img = img / (img + 0.35) * np.float32(1.35)
    img *= _vignette(h, w)[..., None]
    rng = np.random.default_rng(seed)
    img += rng.standard_normal(img.shape, dtype=np.float32) * (0.008 + 0.02 * np.sqrt(np.clip(img, 0, 1)))
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
