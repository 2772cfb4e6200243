"""The ground of the roads: sidewalks, asphalt, medians, lane markings, intersections and
crosswalks, painted into the scene's GroundMap."""
from __future__ import annotations

import numpy as np

from .. import materials as M
from ..world import NO_PAINT, WHITE, YELLOW, GroundMap
from .road_grid import Layout, Road, side


def pave_roads(layout: Layout, ground: GroundMap, rng, near):
    """Sidewalks, roads and their markings, intersections, and crosswalks at the
    intersections within sight of the route (``near``, see ego.NearRoute)."""
    _pave_sidewalks(layout, ground, rng)
    for road in layout.roads:
        _paint_road(ground, road, rng)
    intersections = layout.intersections()
    for h, v in intersections:
        box = _intersection_box(h, v)
        ground.fill(*box, M.ASPHALT)
        ground.paint[ground.cells(*_intersection_box(h, v, margin=5.0))] = NO_PAINT
        ground.paint[ground.cells(*box)] = NO_PAINT
    for h, v in intersections:
        if near(v.c, h.c, 150.0):
            _crosswalks(ground, h, v)


def _pave_sidewalks(layout: Layout, ground: GroundMap, rng):
    for road in layout.roads:
        for s in (-1, 1):
            curb = road.c + s * road.half(s)
            a0, a1 = sorted((curb, curb + s * road.sidewalk))
            # half the sidewalks have a paved furniture strip (other_flat) along the curb
            b0, b1 = sorted((curb, curb + s * 1.5)) if rng.random() < 0.5 else (curb, curb)
            if road.axis == 0:
                ground.fill(road.lo, road.hi, a0, a1, M.TILES)
                ground.fill(road.lo, road.hi, b0, b1, M.COBBLE)
            else:
                ground.fill(a0, a1, road.lo, road.hi, M.TILES)
                ground.fill(b0, b1, road.lo, road.hi, M.COBBLE)


def _paint_road(ground: GroundMap, road: Road, rng):
    """Asphalt, medians, lane markings of one road (markings over its whole length)."""
    a, c = road.axis, road.c

    def rect(u0, u1, v0, v1, material=None, paint=None):
        x0, x1, y0, y1 = (u0, u1, v0, v1) if a == 0 else (v0, v1, u0, u1)
        sl = ground.cells(min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1))
        if material is not None:
            ground.material[sl] = material
        if paint is not None:
            ground.paint[sl] = paint
        return sl

    lo, hi = road.lo, road.hi
    rect(lo, hi, c - road.half(-1), c + road.half(1), M.ASPHALT)
    if road.median_kind in ("raised", "grass"):
        rect(lo, hi, c - road.median / 2, c + road.median / 2, M.COBBLE if road.median_kind == "raised" else M.GRASS)

    def line(v, width=0.15, dashed=False, color=WHITE):
        sl = rect(lo, hi, v - width / 2, v + width / 2)
        along = sl[a]
        centres = (ground.cell_centres_x if a == 0 else ground.cell_centres_y)(along)
        keep = ((centres - lo) % 9.0 < 3.0) if dashed else np.ones(len(centres), bool)
        idx = np.arange(along.start, along.stop)[keep]
        if a == 0:
            ground.paint[idx, sl[1]] = color
        else:
            ground.paint[sl[0], idx] = color

    if road.median_kind == "paint":
        if road.lanes == 1 and rng.random() < 0.5:
            line(c, dashed=True, color=YELLOW)
        else:
            line(c - 0.1, color=YELLOW), line(c + 0.1, color=YELLOW)
    else:
        line(c - road.median / 2 - 0.1, color=YELLOW), line(c + road.median / 2 + 0.1, color=YELLOW)
    for s in (-1, 1):
        for i in range(1, road.lanes):
            line(c + s * (road.median / 2 + road.lane_w * i), dashed=True)
        edge = road.median / 2 + road.lanes * road.lane_w
        line(c + s * (edge - 0.1), dashed=road.park[(s + 1) // 2] > 0)


def _intersection_box(h: Road, v: Road, margin=0.0):
    return (v.c - v.half(-1) - margin, v.c + v.half(1) + margin, h.c - h.half(-1) - margin, h.c + h.half(1) + margin)


def _crosswalks(ground: GroundMap, h: Road, v: Road):
    """Zebra crossings and stop lines on all four approaches of the intersection h x v."""
    for road, cross in ((h, v), (v, h)):
        for end in (-1, 1):
            # crossing band across ``road`` just outside ``cross``
            edge = cross.c + end * cross.half(end)
            u0, u1 = sorted((edge + end * 1.0, edge + end * 4.0))
            stripes_v = np.arange(road.c - road.half(-1) + 0.3, road.c + road.half(1) - 0.3, 1.0)
            for sv in stripes_v:
                x0, x1, y0, y1 = (u0, u1, sv, sv + 0.5) if road.axis == 0 else (sv, sv + 0.5, u0, u1)
                ground.paint[ground.cells(x0, x1, y0, y1)] = WHITE
            # stop line on the lanes that arrive at this end (traffic heading -end)
            s = side(road.axis, -end)
            v0, v1 = sorted((road.c + s * road.median / 2, road.c + s * (road.median / 2 + road.lanes * road.lane_w)))
            w0, w1 = sorted((edge + end * 4.5, edge + end * 4.9))
            x0, x1, y0, y1 = (w0, w1, v0, v1) if road.axis == 0 else (v0, v1, w0, w1)
            ground.paint[ground.cells(x0, x1, y0, y1)] = WHITE
