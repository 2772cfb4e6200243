"""The synthetic world of one scene at any time t: ground map, static primitives, annotated
things (moving or not), the ego's motion and the lighting.

Everything is laid out in a *city frame* (roads along its axes) and placed in the global
(map) frame by a rotation ``theta`` and an offset, so global headings are arbitrary.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...classes import OCC_CLASSES
from . import materials as M
from .motion import Movers
from .primitives import Primitives
from .shapes import Shape

# ground material -> Occ3D class
GROUND_CLASS = np.full(256, OCC_CLASSES.index("terrain"), np.uint8)
GROUND_CLASS[M.ASPHALT] = OCC_CLASSES.index("driveable_surface")
GROUND_CLASS[M.TILES] = OCC_CLASSES.index("sidewalk")
for _m in (M.COBBLE, M.PARKING, M.GRAVEL):
    GROUND_CLASS[_m] = OCC_CLASSES.index("other_flat")
# ground material -> nuScenes-lidarseg index (flat.*)
GROUND_SEG = np.full(256, 27, np.uint8)  # flat.terrain
GROUND_SEG[M.ASPHALT] = 24
GROUND_SEG[M.TILES] = 26
for _m in (M.COBBLE, M.PARKING, M.GRAVEL):
    GROUND_SEG[_m] = 25

NO_PAINT, WHITE, YELLOW = 0, 1, 2


class GroundMap:
    """Rasters over the city frame: ground material and road paint, ``res`` metres per cell,
    indexed [ix, iy] from (x0, y0). Outside the raster the ground is grass."""

    def __init__(self, x0, y0, x1, y1, res=0.1):
        self.x0, self.y0, self.res = float(x0), float(y0), float(res)
        self.nx, self.ny = int(np.ceil((x1 - x0) / res)), int(np.ceil((y1 - y0) / res))
        self.material = np.full((self.nx, self.ny), M.GRASS, np.uint8)
        self.paint = np.zeros((self.nx, self.ny), np.uint8)

    def _span(self, lo, hi, origin, n):
        return (int(np.clip(np.floor((lo - origin) / self.res + 0.5), 0, n)),
                int(np.clip(np.floor((hi - origin) / self.res + 0.5), 0, n)))

    def cells(self, x0, x1, y0, y1):
        """Slices of the cells whose centres lie in [x0, x1) x [y0, y1)."""
        ix = self._span(x0, x1, self.x0, self.nx)
        iy = self._span(y0, y1, self.y0, self.ny)
        return slice(*ix), slice(*iy)

    def fill(self, x0, x1, y0, y1, material):
        self.material[self.cells(min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1))] = material

    def cell_centres_x(self, sl):
        return self.x0 + (np.arange(sl.start, sl.stop) + 0.5) * self.res

    def cell_centres_y(self, sl):
        return self.y0 + (np.arange(sl.start, sl.stop) + 0.5) * self.res

    def lookup(self, x, y):
        """(material, paint) at city-frame points (arrays of the same shape)."""
        ix = np.floor((np.asarray(x) - self.x0) / self.res).astype(np.int64)
        iy = np.floor((np.asarray(y) - self.y0) / self.res).astype(np.int64)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        ixc, iyc = np.clip(ix, 0, self.nx - 1), np.clip(iy, 0, self.ny - 1)
        mat = np.where(inside, self.material[ixc, iyc], M.GRASS)
        paint = np.where(inside, self.paint[ixc, iyc], NO_PAINT)
        return mat, paint


@dataclass
class Lighting:
    sun: np.ndarray          # unit vector towards the sun (global)
    sun_color: np.ndarray    # RGB irradiance of the sun
    ambient: np.ndarray      # RGB sky irradiance
    zenith: np.ndarray       # sky colour overhead
    horizon: np.ndarray      # sky colour at the horizon
    fog_distance: float      # metres (aerial perspective)
    exposure: float
    cloudiness: float        # 0 clear .. 1 overcast


@dataclass
class Thing:
    """An annotated object: its shape and the mover (index into World.movers) it rides on."""
    shape: Shape
    mover: int
    kind: str  # "vehicle" | "pedestrian" | "cycle" | "static": picks the nuScenes attribute


class World:
    def __init__(self, name, duration, theta, offset, ground: GroundMap, static_city: Primitives,
                 things: list[Thing], movers: Movers, ego: Movers, lighting: Lighting, texture_seed: int = 0):
        self.name = name
        self.texture_seed = int(texture_seed)
        self.duration = float(duration)
        self.theta = float(theta)
        self.offset = np.asarray(offset, float)
        self.R = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
        self.ground = ground
        self.things = things
        self.movers = movers
        self.ego = ego
        self.lighting = lighting
        self.static = self._to_global(static_city)
        # all parts of all things, concatenated once; posed per time in prims_at
        parts, owner = [], []
        for k, thing in enumerate(things):
            p = thing.shape.parts.take(slice(None))
            p.inst = np.full(len(p), k, np.int32)
            parts.append(p)
            owner.append(np.full(len(p), k))
        self._parts = Primitives.concat(parts)
        self._owner = np.concatenate(owner) if owner else np.zeros(0, int)
        self._thing_mover = np.array([t.mover for t in things], int)
        self.wlh = np.array([t.shape.wlh for t in things], float).reshape(-1, 3)

    # -- frames ------------------------------------------------------------------------
    def city_to_global_xy(self, xy):
        return np.asarray(xy) @ self.R.T + self.offset

    def global_to_city_xy(self, xy):
        return (np.asarray(xy) - self.offset) @ self.R

    def _to_global(self, p: Primitives) -> Primitives:
        q = p.take(slice(None))
        q.center = q.center.copy()
        q.center[:, :2] = self.city_to_global_xy(p.center[:, :2])
        q.yaw = p.yaw + self.theta
        return q

    # -- state at time t ---------------------------------------------------------------
    def thing_states(self, t):
        """Global (bottom-centre xy [K, 2], yaw [K], velocity xy [K, 2]) of every thing."""
        xy, yaw, vel = self.movers.pose(t)
        m = self._thing_mover
        return self.city_to_global_xy(xy[m]), yaw[m] + self.theta, vel[m] @ self.R.T

    def boxes(self, t):
        """Global 3D boxes of all things: centre [K, 3], yaw [K], wlh [K, 3], velocity [K, 2]."""
        xy, yaw, vel = self.thing_states(t)
        centre = np.concatenate([xy, self.wlh[:, 2:3] / 2], 1)
        return centre, yaw, self.wlh, vel

    def prims_at(self, t) -> Primitives:
        """Every primitive of the world at time t (global)."""
        if not len(self._parts):
            return self.static
        xy, yaw, _ = self.thing_states(t)
        p = self._parts.take(slice(None))
        o = self._owner
        c, s = np.cos(yaw[o]), np.sin(yaw[o])
        lx, ly = self._parts.center[:, 0], self._parts.center[:, 1]
        p.center = np.stack([xy[o, 0] + c * lx - s * ly, xy[o, 1] + s * lx + c * ly,
                             self._parts.center[:, 2]], -1)
        p.yaw = self._parts.yaw + yaw[o]
        return Primitives.concat([self.static, p])

    def ego_pose(self, t) -> np.ndarray:
        """T_global_from_ego (4x4) at time t; the ego stays on the flat ground (z = 0)."""
        xy, yaw, _ = self.ego.pose(t)
        g = self.city_to_global_xy(xy[0])
        a = yaw[0] + self.theta
        T = np.eye(4)
        T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        T[:2, 3] = g
        return T

    def ground_at(self, x_global, y_global):
        """(material, paint) at global xy."""
        pts = np.stack([np.ravel(x_global), np.ravel(y_global)], -1)
        c = self.global_to_city_xy(pts)
        mat, paint = self.ground.lookup(c[:, 0], c[:, 1])
        shape = np.shape(x_global)
        return mat.reshape(shape), paint.reshape(shape)
