"""Everything static along the streets: buildings, parks, parking lots and building sites on
the blocks; trees, lamps, signs, bins, bicycle racks and bus shelters on the sidewalks;
traffic lights at intersections and barriers on barrier medians.

Unannotated stuff (manmade, vegetation) goes into ``layout.static`` as primitives;
annotated objects (parked cars, bins, racks, barriers) into ``layout.things``.
"""
from __future__ import annotations

import numpy as np

from ....classes import OCC_CLASSES
from ...lidarseg import lidarseg_index
from .. import materials as M
from .. import shapes
from ..motion import Path
from ..primitives import BOX, ELLIPSOID, FRUSTUM, make
from ..world import GroundMap
from .road_grid import BORDER, Layout, Road

MANMADE, VEGETATION = OCC_CLASSES.index("manmade"), OCC_CLASSES.index("vegetation")
SEG_MANMADE, SEG_VEGETATION = lidarseg_index("static.manmade"), lidarseg_index("static.vegetation")
FACADE_COLORS = ((0.82, 0.78, 0.7), (0.7, 0.62, 0.52), (0.6, 0.35, 0.28), (0.85, 0.85, 0.82),
                 (0.55, 0.57, 0.6), (0.9, 0.82, 0.6), (0.45, 0.42, 0.4), (0.75, 0.7, 0.75))
FOLIAGE_COLORS = ((0.18, 0.35, 0.12), (0.25, 0.42, 0.15), (0.12, 0.28, 0.12), (0.35, 0.45, 0.18))
SIGN_COLORS = ((0.1, 0.25, 0.7), (0.8, 0.1, 0.1), (0.95, 0.95, 0.95), (0.95, 0.8, 0.1), (0.1, 0.5, 0.2))


# -- stuff builders (static, unannotated): manmade and vegetation ------------------------------

def _stuff(layout, kind, center, half, label, material, color, yaw=0.0, taper=1.0):
    seg = SEG_MANMADE if label == MANMADE else SEG_VEGETATION
    layout.static.append(make(kind, center, half, yaw, label, seg, material, color, taper=taper))


def tree(layout, rng, x, y):
    h_trunk = rng.uniform(2.2, 3.4)
    r_trunk = rng.uniform(0.12, 0.25)
    _stuff(layout, FRUSTUM, (x, y, h_trunk / 2 + 0.2), (r_trunk, r_trunk, h_trunk / 2 + 0.2), VEGETATION,
           M.BARK, (0.3, 0.22, 0.15), taper=0.7)
    color = np.asarray(FOLIAGE_COLORS[rng.integers(len(FOLIAGE_COLORS))]) * rng.uniform(0.8, 1.2)
    if rng.random() < 0.25:  # conifer
        r, h = rng.uniform(1.2, 2.2), rng.uniform(4, 8)
        _stuff(layout, FRUSTUM, (x, y, h_trunk * 0.6 + h / 2), (r, r, h / 2), VEGETATION, M.FOLIAGE, color, taper=0.0)
    else:
        r = rng.uniform(1.5, 3.2)
        rz = r * rng.uniform(0.8, 1.3)
        _stuff(layout, ELLIPSOID, (x, y, h_trunk + rz), (r, r * rng.uniform(0.85, 1.15), rz), VEGETATION,
               M.FOLIAGE, color)
    layout.obstacles.append((x, y, r_trunk + 0.3))


def lamp(layout, rng, x, y, toward):
    """Street lamp at (x, y) with its arm pointing along the unit 2D vector ``toward``."""
    h = rng.uniform(7.0, 9.0)
    _stuff(layout, FRUSTUM, (x, y, h / 2), (0.12, 0.12, h / 2), MANMADE, M.METAL, (0.35, 0.37, 0.4), taper=0.6)
    yaw = float(np.arctan2(toward[1], toward[0]))
    arm = 1.6
    _stuff(layout, BOX, (x + toward[0] * arm / 2, y + toward[1] * arm / 2, h - 0.1), (arm / 2, 0.05, 0.05),
           MANMADE, M.METAL, (0.35, 0.37, 0.4), yaw=yaw)
    _stuff(layout, BOX, (x + toward[0] * arm, y + toward[1] * arm, h - 0.25), (0.35, 0.15, 0.1),
           MANMADE, M.LAMP, (0.9, 0.9, 0.85), yaw=yaw)
    layout.obstacles.append((x, y, 0.5))


def sign(layout, rng, x, y, facing_yaw):
    h = rng.uniform(2.3, 2.9)
    _stuff(layout, FRUSTUM, (x, y, h / 2), (0.05, 0.05, h / 2), MANMADE, M.METAL, (0.55, 0.55, 0.57))
    color = SIGN_COLORS[rng.integers(len(SIGN_COLORS))]
    size = rng.uniform(0.28, 0.4)
    _stuff(layout, BOX, (x, y, h + size), (0.03, size, size), MANMADE, M.SIGN, color, yaw=facing_yaw)
    layout.obstacles.append((x, y, 0.4))


def traffic_light(layout, rng, x, y, facing_yaw, arm_dir=None, arm_len=0.0):
    h = rng.uniform(3.5, 5.0)
    _stuff(layout, FRUSTUM, (x, y, h / 2), (0.1, 0.1, h / 2), MANMADE, M.METAL, (0.2, 0.2, 0.2))
    hx, hy = x, y
    if arm_dir is not None and arm_len > 0:
        yaw = float(np.arctan2(arm_dir[1], arm_dir[0]))
        _stuff(layout, BOX, (x + arm_dir[0] * arm_len / 2, y + arm_dir[1] * arm_len / 2, h - 0.2),
               (arm_len / 2, 0.06, 0.06), MANMADE, M.METAL, (0.2, 0.2, 0.2), yaw=yaw)
        hx, hy = x + arm_dir[0] * arm_len, y + arm_dir[1] * arm_len
    _stuff(layout, BOX, (hx, hy, h - 0.75), (0.15, 0.18, 0.5), MANMADE, M.METAL, (0.08, 0.08, 0.08), yaw=facing_yaw)
    layout.obstacles.append((x, y, 0.5))


def building(layout, rng, x0, x1, y0, y1, height):
    color = np.asarray(FACADE_COLORS[rng.integers(len(FACADE_COLORS))]) * rng.uniform(0.85, 1.1)
    _stuff(layout, BOX, ((x0 + x1) / 2, (y0 + y1) / 2, height / 2), (abs(x1 - x0) / 2, abs(y1 - y0) / 2, height / 2),
           MANMADE, M.FACADE, np.clip(color, 0, 1))


def hedge(layout, x0, x1, y0, y1, rng):
    h = rng.uniform(0.8, 1.6)
    color = np.asarray(FOLIAGE_COLORS[rng.integers(len(FOLIAGE_COLORS))]) * 0.8
    _stuff(layout, BOX, ((x0 + x1) / 2, (y0 + y1) / 2, h / 2), (abs(x1 - x0) / 2, abs(y1 - y0) / 2, h / 2),
           VEGETATION, M.FOLIAGE, color)


def fence(layout, x0, x1, y0, y1, rng):
    h = rng.uniform(1.2, 2.2)
    half = (max(abs(x1 - x0) / 2, 0.03), max(abs(y1 - y0) / 2, 0.03), h / 2)
    _stuff(layout, BOX, ((x0 + x1) / 2, (y0 + y1) / 2, h / 2), half,
           MANMADE, M.FENCE, (0.5, 0.5, 0.48))


def bus_shelter(layout, x, y, yaw, away):
    """Roof and back wall; ``away`` is the unit 2D vector from the road to the wall."""
    _stuff(layout, BOX, (x, y, 2.45), (2.0, 0.8, 0.06), MANMADE, M.METAL, (0.4, 0.42, 0.45), yaw=yaw)
    _stuff(layout, BOX, (x + away[0] * 0.75, y + away[1] * 0.75, 1.2), (2.0, 0.04, 1.2), MANMADE, M.GLASS,
           (0.5, 0.55, 0.6), yaw=yaw)
    layout.obstacles.append((x, y, 2.2))


# -- blocks ------------------------------------------------------------------------------------

def fill_blocks(layout: Layout, ground: GroundMap, rng, near):
    """Every block between the roads' sidewalks: furnished (``_fill_block``) where it can be
    seen from the route (``near``, see ego.NearRoute), grass elsewhere."""
    x0, x1, y0, y1 = layout.x0, layout.x1, layout.y0, layout.y1
    xs = [x0 - BORDER] + [r.c for r in layout.v_roads] + [x1 + BORDER]
    ys = [y0 - BORDER] + [r.c for r in layout.h_roads] + [y1 + BORDER]
    vr = {r.c: r for r in layout.v_roads}
    hr = {r.c: r for r in layout.h_roads}
    for i in range(len(xs) - 1):
        for j in range(len(ys) - 1):
            bx0 = xs[i] + (vr[xs[i]].half(1) + vr[xs[i]].sidewalk if xs[i] in vr else 0)
            bx1 = xs[i + 1] - (vr[xs[i + 1]].half(-1) + vr[xs[i + 1]].sidewalk if xs[i + 1] in vr else 0)
            by0 = ys[j] + (hr[ys[j]].half(1) + hr[ys[j]].sidewalk if ys[j] in hr else 0)
            by1 = ys[j + 1] - (hr[ys[j + 1]].half(-1) + hr[ys[j + 1]].sidewalk if ys[j + 1] in hr else 0)
            cx, cy = np.clip((bx0 + bx1) / 2, bx0, bx1), np.clip((by0 + by1) / 2, by0, by1)
            corner_near = any(near(px, py, 140.0) for px in (bx0, bx1, cx) for py in (by0, by1, cy))
            if corner_near:
                _fill_block(layout, ground, rng, bx0, bx1, by0, by1, near(cx, cy, 120.0))
            else:
                ground.fill(bx0, bx1, by0, by1, M.GRASS)


def fill_countryside(layout: Layout, ground: GroundMap, rng, near):
    """The open road's surroundings: grass, and trees scattered beside the road where they
    can be seen from the route (``near``)."""
    ground.fill(layout.x0 - BORDER, layout.x1 + BORDER, layout.y0 - BORDER, layout.y1 + BORDER,
                M.GRASS)
    road = layout.main
    for s in (-1, 1):
        u = road.lo
        while u < road.hi:
            u += rng.uniform(6.0, 40.0)
            y = road.c + s * (road.half(s) + road.sidewalk + rng.uniform(2.0, 25.0))
            if near(u, y, 120.0):
                tree(layout, rng, u, y)


def _fill_block(layout, ground, rng, bx0, bx1, by0, by1, near_route):
    """One block inside its sidewalks: buildings along the edges, or a park, parking lot or
    building site. ``near_route``: add parked cars / machines only where they can be seen."""
    w, d = bx1 - bx0, by1 - by0
    if w < 8 or d < 8:
        ground.fill(bx0, bx1, by0, by1, M.GRASS)
        return
    kind = rng.choice(["buildings"] * 6 + ["park", "parking", "site"])
    if kind == "park":
        _park(layout, ground, rng, bx0, bx1, by0, by1)
    elif kind == "parking":
        _parking_lot(layout, ground, rng, bx0, bx1, by0, by1, near_route)
    elif kind == "site":
        _building_site(layout, ground, rng, bx0, bx1, by0, by1, near_route)
    else:
        _buildings(layout, ground, rng, bx0, bx1, by0, by1)


def _park(layout, ground, rng, bx0, bx1, by0, by1):
    """Grass with trees, a paved path across the middle, a hedge along one edge."""
    w, d = bx1 - bx0, by1 - by0
    ground.fill(bx0, bx1, by0, by1, M.GRASS)
    ground.fill(bx0, bx1, (by0 + by1) / 2 - 1.2, (by0 + by1) / 2 + 1.2, M.TILES)
    for _ in range(int(w * d / 120)):
        x, y = rng.uniform(bx0 + 2, bx1 - 2), rng.uniform(by0 + 2, by1 - 2)
        if abs(y - (by0 + by1) / 2) > 2.5:
            tree(layout, rng, x, y)
    hedge(layout, bx0 + 1, bx1 - 1, by0 + 0.6, by0 + 1.4, rng)


def _parking_lot(layout, ground, rng, bx0, bx1, by0, by1, near_route):
    """Two rows of stalls (cars in about half of them near the route) and lamps between."""
    ground.fill(bx0, bx1, by0, by1, M.PARKING)
    for x in np.arange(bx0 + 3, bx1 - 3, 2.7):
        for y in (by0 + 4, by1 - 4):
            if near_route and rng.random() < 0.55:
                shape = shapes.car(rng)
                layout.things.append((shape, Path((x, y), np.pi / 2 * rng.choice([-1, 1]), [("line", 0.01)]),
                                      np.zeros(2), 0.0, "vehicle", None))
    for x in np.arange(bx0 + 10, bx1 - 5, 25):
        lamp(layout, rng, x, (by0 + by1) / 2, (0, 1))


def _building_site(layout, ground, rng, bx0, bx1, by0, by1, near_route):
    """Dirt and gravel behind fences; near the route a construction machine and a container."""
    w = bx1 - bx0
    ground.fill(bx0, bx1, by0, by1, M.DIRT)
    ground.fill(bx0 + 4, bx1 - 4, by0 + 4, by1 - 4, M.GRAVEL)
    fence(layout, bx0 + 0.5, bx1 - 0.5, by0 + 0.5, by0 + 0.55, rng)
    fence(layout, bx0 + 0.5, bx1 - 0.5, by1 - 0.55, by1 - 0.5, rng)
    if near_route:
        shape = shapes.construction_vehicle(rng)
        x, y = (bx0 + bx1) / 2 + rng.uniform(-w / 4, w / 4), (by0 + by1) / 2
        layout.things.append((shape, Path((x, y), rng.uniform(-np.pi, np.pi), [("line", 0.01)]), np.zeros(2),
                              0.0, "vehicle", None))
        building(layout, rng, x + 6, x + 12, y - 1.5, y + 1.5, 2.6)  # site container


def _buildings(layout, ground, rng, bx0, bx1, by0, by1):
    """Buildings along the edges facing roads, a courtyard inside."""
    w, d = bx1 - bx0, by1 - by0
    ground.fill(bx0, bx1, by0, by1, M.GRASS if rng.random() < 0.5 else M.COBBLE)
    depth = min(rng.uniform(10, 22), d / 2 - 1, w / 2 - 1)
    tall = rng.uniform(0.3, 1.0)
    for y_lo, y_hi in ((by0, by0 + depth), (by1 - depth, by1)):
        x = bx0 + rng.uniform(0, 3)
        while x < bx1 - 6:
            bw = min(rng.uniform(8, 30), bx1 - x)
            setback = rng.uniform(0, 2.5) if rng.random() < 0.4 else 0.0
            height = rng.choice([rng.uniform(4, 8), rng.uniform(9, 20), rng.uniform(20, 35) * tall])
            yy0, yy1 = (y_lo + setback, y_hi) if y_lo == by0 else (y_lo, y_hi - setback)
            if setback:
                ground.fill(x, x + bw, by0 if y_lo == by0 else by1 - setback, (by0 + setback) if y_lo == by0 else by1,
                            M.TILES)
            building(layout, rng, x, x + bw, yy0, yy1, height)
            x += bw + (rng.uniform(2, 8) if rng.random() < 0.35 else 0.0)
    for x_lo, x_hi in ((bx0, bx0 + depth), (bx1 - depth, bx1)):
        if d - 2 * depth > 6:
            building(layout, rng, x_lo, x_hi, by0 + depth + 0.5, by1 - depth - 0.5, rng.uniform(5, 18))


# -- along the streets ----------------------------------------------------------------------

def place_street_furniture(layout: Layout, rng, near):
    """Sidewalk furniture and barrier medians along every road, traffic lights at the
    intersections, where they can be seen from the route (``near``, see ego.NearRoute)."""
    for road in layout.roads:
        crossing = layout.v_roads if road.axis == 0 else layout.h_roads
        spans = [(c.c - c.half(-1) - 5, c.c + c.half(1)) for c in crossing]
        _sidewalk_furniture(layout, rng, road, spans, near)
        if road.median_kind == "barrier":
            _barrier_median(layout, rng, road, spans, near)
    _traffic_lights(layout, rng, near)


def _sidewalk_furniture(layout, rng, road: Road, intersections, near):
    """Trees, lamps, signs, bins, racks, shelters along both sidewalks of ``road``,
    outside intersections. ``near(x, y)`` says whether a point is within sight of the route."""
    a = road.axis
    for s in (-1, 1):
        curb = road.c + s * road.half(s)
        furn = curb + s * 0.8               # furniture zone centre line
        toward_road = np.array((0, -s)) if a == 0 else np.array((-s, 0))
        u = road.lo + rng.uniform(0, 5)
        tree_gap = rng.uniform(7, 14) if rng.random() < 0.7 else None
        next_lamp = u + rng.uniform(0, 25)
        next_tree = u if tree_gap else np.inf
        while u < road.hi:
            u += 1.0
            if any(lo - 2 < u < hi + 6 for lo, hi in intersections):
                continue
            x, y = (u, furn) if a == 0 else (furn, u)
            if not near(x, y):
                continue
            if u >= next_lamp:
                lamp(layout, rng, x, y, toward_road)
                next_lamp = u + rng.uniform(24, 36)
                continue
            if u >= next_tree:
                tree(layout, rng, x, y)
                next_tree = u + tree_gap * rng.uniform(0.8, 1.2)
                continue
            r = rng.random()
            if r < 0.012:
                sign(layout, rng, x, y, road.heading(1) + np.pi * (rng.random() < 0.5))
            elif r < 0.02:
                shape = shapes.trash_bin(rng)
                layout.things.append((shape, Path((x, y), road.heading(1), [("line", 0.01)]), np.zeros(2), 0.0,
                                      "static", None))
            elif r < 0.024:
                shape = shapes.bicycle_rack(rng)
                group = ("rack", road.axis, road.c, s, u)   # the rack and its bicycles stay or go together
                layout.things.append((shape, Path((x, y), road.heading(1), [("line", 0.01)]), np.zeros(2), 0.0,
                                      "static", group))
                for k in range(int(rng.integers(0, 4))):
                    along = -shape.wlh[1] / 2 + 0.5 + 0.9 * k
                    if along > shape.wlh[1] / 2:
                        break
                    bx, by = (x + along, y - s * 0.45) if a == 0 else (x - s * 0.45, y + along)
                    layout.things.append((shapes.bicycle(rng, rider=False), Path((bx, by), road.heading(1),
                                          [("line", 0.01)]), np.zeros(2), 0.0, "cycle", group))
                u += shape.wlh[1]
            elif r < 0.027:
                away = np.array((0.0, s)) if a == 0 else np.array((float(s), 0.0))
                bus_shelter(layout, x + away[0] * 1.2, y + away[1] * 1.2, road.heading(1), away)
                u += 5


def _barrier_median(layout, rng, road: Road, intersections, near):
    """Barriers end to end along the centre of ``road``, outside intersections."""
    u = road.lo
    while u < road.hi:
        shape = shapes.barrier(rng)
        xx, yy = (u, road.c) if road.axis == 0 else (road.c, u)
        if near(xx, yy, 80.0) and not any(lo - 2 < u < hi + 6 for lo, hi in intersections):
            layout.things.append((shape, Path((xx, yy), road.heading(1), [("line", 0.01)]),
                                  np.zeros(2), 0.0, "static", None))
        u += shape.wlh[1] + 0.2


def _traffic_lights(layout: Layout, rng, near):
    """Up to four lights (some on an arm over the road) at each intersection near the route."""
    for h, v in layout.intersections():
        if not near(v.c, h.c, 120.0):
            continue
        for sx in (-1, 1):
            for sy in (-1, 1):
                px = v.c + sx * (v.half(sx) + 0.8)
                py = h.c + sy * (h.half(sy) + 0.8)
                if rng.random() < 0.8:
                    arm = (0.0, -sy) if rng.random() < 0.5 else None
                    traffic_light(layout, rng, px, py, np.arctan2(-sy, -sx), arm, h.lanes * h.lane_w * 0.8)
