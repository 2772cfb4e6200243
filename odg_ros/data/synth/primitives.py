"""Solid primitives the synthetic world is built of, as a structure of arrays.

Every primitive has a local frame: a centre, a yaw about the vertical axis, and half
extents (hx, hy, hz) along its local axes. In the *unit frame* (local coordinates divided
by the half extents) the primitive is

* BOX:       the cube [-1, 1]^3;
* FRUSTUM:   a vertical truncated cone, z in [-1, 1], radius 1 at z = -1 and ``taper`` at
             z = +1 (taper = 1: a cylinder, taper = 0: a cone);
* ELLIPSOID: the unit sphere.

Rays, voxel tests and normals all work in the unit frame: the map local -> unit is affine,
so ray parameters t are the same in both frames.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

BOX, FRUSTUM, ELLIPSOID = 0, 1, 2


@dataclass
class Primitives:
    """P primitives, global frame. Per-primitive appearance/semantics travel with them."""
    kind: np.ndarray      # int8 [P]
    center: np.ndarray    # float64 [P, 3]
    half: np.ndarray      # float64 [P, 3] half extents > 0
    yaw: np.ndarray       # float64 [P]
    taper: np.ndarray     # float64 [P] frustum top/bottom radius ratio (1 for other kinds)
    label: np.ndarray     # uint8 [P] Occ3D label
    seg: np.ndarray       # uint8 [P] nuScenes-lidarseg general index
    material: np.ndarray  # int16 [P] shading.Material
    color: np.ndarray     # float32 [P, 3] base albedo in [0, 1]
    inst: np.ndarray      # int32 [P] annotated object index in the scene, -1 for stuff

    def __len__(self) -> int:
        return len(self.kind)

    @staticmethod
    def empty() -> "Primitives":
        return Primitives(np.zeros(0, np.int8), np.zeros((0, 3)), np.ones((0, 3)), np.zeros(0),
                          np.ones(0), np.zeros(0, np.uint8), np.zeros(0, np.uint8),
                          np.zeros(0, np.int16), np.zeros((0, 3), np.float32), np.zeros(0, np.int32))

    @staticmethod
    def concat(parts: list["Primitives"]) -> "Primitives":
        parts = [p for p in parts if len(p)]
        if not parts:
            return Primitives.empty()
        return Primitives(*[np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Primitives)])

    def take(self, index) -> "Primitives":
        return Primitives(*[getattr(self, f.name)[index] for f in fields(Primitives)])

    def corners(self) -> np.ndarray:
        """[P, 8, 3] corners of each primitive's oriented bounding box (global)."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        local = signs[None] * self.half[:, None, :]
        c, s = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        x = c * local[..., 0] - s * local[..., 1]
        y = s * local[..., 0] + c * local[..., 1]
        return np.stack([x, y, local[..., 2]], -1) + self.center[:, None, :]

    def to_unit(self, points, index) -> np.ndarray:
        """Global points [Q, 3] -> unit frame of primitive ``index[q]`` (float64)."""
        d = points - self.center[index]
        c, s = np.cos(self.yaw[index]), np.sin(self.yaw[index])
        x = c * d[:, 0] + s * d[:, 1]
        y = -s * d[:, 0] + c * d[:, 1]
        return np.stack([x, y, d[:, 2]], -1) / self.half[index]


def make(kind, center, half, yaw, label, seg, material, color, inst=-1, taper=1.0) -> Primitives:
    """One primitive (convenience for world building)."""
    return Primitives(np.array([kind], np.int8), np.array([center], float), np.array([half], float),
                      np.array([yaw], float), np.array([taper], float), np.array([label], np.uint8),
                      np.array([seg], np.uint8), np.array([material], np.int16),
                      np.array([color], np.float32), np.array([inst], np.int32))


def contains(prims: Primitives, points, index, inflate: float = 0.0) -> np.ndarray:
    """Whether global points [Q, 3] lie in primitive ``index[q]`` grown by ``inflate`` metres
    along its local axes (boxes: exact Minkowski growth by a cube; round kinds: radii + inflate).
    A negative ``inflate`` shrinks; it must stay above minus the smallest half extent."""
    half = prims.half[index] + inflate
    d = points - prims.center[index]
    c, s = np.cos(prims.yaw[index]), np.sin(prims.yaw[index])
    u = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], -1) / half
    kind = prims.kind[index]
    inside = np.zeros(len(index), bool)
    box = kind == BOX
    inside[box] = np.all(np.abs(u[box]) <= 1.0, axis=1)
    ell = kind == ELLIPSOID
    inside[ell] = np.einsum("ij,ij->i", u[ell], u[ell]) <= 1.0
    fru = kind == FRUSTUM
    if fru.any():
        uf = u[fru]
        taper = prims.taper[index][fru]
        # radius at height z in the grown frustum's unit frame: the unit radius is grown by the
        # same absolute margin, so interpolate the grown radii
        hx = prims.half[index][fru, 0]
        r_bot = (hx + inflate) / (hx + inflate)
        r_top = np.maximum(hx * taper + inflate, 0) / (hx + inflate)
        r = r_bot + (r_top - r_bot) * (uf[:, 2] + 1) / 2
        inside[fru] = (np.abs(uf[:, 2]) <= 1.0) & (uf[:, 0] ** 2 + uf[:, 1] ** 2 <= r ** 2)
    return inside
