"""Procedural layout of one scene: a grid of roads (lanes, medians, parking lanes,
sidewalks, crosswalks, markings), blocks (buildings, parks, parking lots, building sites),
street furniture, and the traffic (ego route, vehicles, cyclists, pedestrians, parked cars,
construction zones). All in the city frame; ``build_world`` returns a World.

Right-hand traffic. A road along x (axis 0) or y (axis 1) has ``lanes`` lanes per
direction; lane i (0 = next to the centre) of the direction ``d`` (+1 / -1 along the axis)
lies on side ``side(axis, d)`` of the centre line.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from odg_ros.classes import OCC_CLASSES
from odg_ros.data.lidarseg import lidarseg_index
from odg_ros.data.synth import materials as M
from odg_ros.data.synth import shapes
from odg_ros.data.synth.motion import Movers, Path, speed_profile
from odg_ros.data.synth.primitives import BOX, ELLIPSOID, FRUSTUM, Primitives, make
from odg_ros.data.synth.world import NO_PAINT, WHITE, YELLOW, GroundMap, Lighting, Thing, World

MANMADE, VEGETATION = OCC_CLASSES.index("manmade"), OCC_CLASSES.index("vegetation")
SEG_MANMADE, SEG_VEGETATION = lidarseg_index("static.manmade"), lidarseg_index("static.vegetation")
FACADE_COLORS = ((0.82, 0.78, 0.7), (0.7, 0.62, 0.52), (0.6, 0.35, 0.28), (0.85, 0.85, 0.82),
                 (0.55, 0.57, 0.6), (0.9, 0.82, 0.6), (0.45, 0.42, 0.4), (0.75, 0.7, 0.75))
FOLIAGE_COLORS = ((0.18, 0.35, 0.12), (0.25, 0.42, 0.15), (0.12, 0.28, 0.12), (0.35, 0.45, 0.18))
SIGN_COLORS = ((0.1, 0.25, 0.7), (0.8, 0.1, 0.1), (0.95, 0.95, 0.95), (0.95, 0.8, 0.1), (0.1, 0.5, 0.2))


def side(axis, direction):
    """Which side of a road's centre line (-1 / +1 in the cross coordinate) carries the
    traffic heading ``direction`` along ``axis`` (right-hand traffic)."""
    return -direction if axis == 0 else direction


@dataclass
class Road:
    axis: int            # 0: along x (centre line y = c), 1: along y (x = c)
    c: float
    lanes: int
    lane_w: float
    median: float
    median_kind: str     # "paint" | "raised" | "grass" | "barrier"
    park: tuple          # parking lane width on side (-1, +1), 0 = none
    sidewalk: float
    lo: float = 0.0      # extent along the axis
    hi: float = 0.0

    def half(self, s):
        """Centre line to curb on side s (-1 / +1)."""
        return self.median / 2 + self.lanes * self.lane_w + self.park[(s + 1) // 2]

    def lane_offset(self, lane, s):
        return s * (self.median / 2 + self.lane_w * (lane + 0.5))

    def heading(self, direction):
        return (0.0 if direction > 0 else np.pi) if self.axis == 0 else (np.pi / 2 if direction > 0 else -np.pi / 2)


@dataclass
class Layout:
    h_roads: list
    v_roads: list
    x0: float
    x1: float
    y0: float
    y1: float
    static: list = field(default_factory=list)       # Primitives (stuff)
    things: list = field(default_factory=list)       # (Shape, Path, speeds, s0, kind, group)
    obstacles: list = field(default_factory=list)    # (x, y, radius) static no-go discs


def _random_road(rng, axis, c, main=False):
    lanes = int(rng.choice([1, 2, 2, 3] if main else [1, 1, 2]))
    lane_w = rng.uniform(3.1, 3.6)
    median_kind = str(rng.choice(["paint", "paint", "raised", "grass", "barrier"] if lanes > 1 else ["paint"]))
    median = {"paint": 0.3, "raised": rng.uniform(1.2, 2.5), "grass": rng.uniform(2.5, 5.0),
              "barrier": 0.9}[median_kind]
    park = tuple(float(rng.uniform(2.2, 2.6)) if rng.random() < 0.5 else 0.0 for _ in range(2))
    return Road(axis, float(c), lanes, float(lane_w), float(median), median_kind, park,
                float(rng.uniform(3.0, 5.5)))


def _road_positions(rng, lo, hi, spacing, anchor=0.0):
    """Road centre coordinates covering [lo, hi] with random spacing, one at ``anchor``."""
    pos = [anchor]
    while pos[-1] < hi:
        pos.append(pos[-1] + rng.uniform(*spacing))
    while pos[0] > lo:
        pos.insert(0, pos[0] - rng.uniform(*spacing))
    return pos


# ---------------------------------------------------------------------------------------
# stuff builders (static, unannotated): manmade and vegetation

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


# ---------------------------------------------------------------------------------------
# ground painting

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


# ---------------------------------------------------------------------------------------
# blocks

def _fill_block(layout, ground, rng, bx0, bx1, by0, by1, near_route):
    """One block inside its sidewalks: buildings along the edges, or a park, parking lot or
    building site. ``near_route``: add parked cars / people only where they can be seen."""
    w, d = bx1 - bx0, by1 - by0
    if w < 8 or d < 8:
        ground.fill(bx0, bx1, by0, by1, M.GRASS)
        return
    kind = rng.choice(["buildings"] * 6 + ["park", "parking", "site"])
    if kind == "park":
        ground.fill(bx0, bx1, by0, by1, M.GRASS)
        ground.fill(bx0, bx1, (by0 + by1) / 2 - 1.2, (by0 + by1) / 2 + 1.2, M.TILES)
        for _ in range(int(w * d / 120)):
            x, y = rng.uniform(bx0 + 2, bx1 - 2), rng.uniform(by0 + 2, by1 - 2)
            if abs(y - (by0 + by1) / 2) > 2.5:
                tree(layout, rng, x, y)
        hedge(layout, bx0 + 1, bx1 - 1, by0 + 0.6, by0 + 1.4, rng)
        return
    if kind == "parking":
        ground.fill(bx0, bx1, by0, by1, M.PARKING)
        for x in np.arange(bx0 + 3, bx1 - 3, 2.7):
            for y in (by0 + 4, by1 - 4):
                if near_route and rng.random() < 0.55:
                    shape = shapes.car(rng)
                    layout.things.append((shape, Path((x, y), np.pi / 2 * rng.choice([-1, 1]), [("line", 0.01)]),
                                          np.zeros(2), 0.0, "vehicle", None))
        for x in np.arange(bx0 + 10, bx1 - 5, 25):
            lamp(layout, rng, x, (by0 + by1) / 2, (0, 1))
        return
    if kind == "site":
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
        return
    # buildings along the edges facing roads, courtyard inside
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


# ---------------------------------------------------------------------------------------
# furniture along sidewalks

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


# ---------------------------------------------------------------------------------------
# traffic

def _static(layout, shape, xy, yaw, kind="static"):
    layout.things.append((shape, Path(xy, yaw, [("line", 0.01)]), np.zeros(2), 0.0, kind, None))


def _construction_zone(layout, rng, road: Road, direction, u0, zlen):
    """Close the outer lane of ``road``'s carriageway heading ``direction`` over [u0, u0 + zlen]:
    barriers along the lane's inner edge, a cone taper upstream, a construction vehicle and
    workers inside."""
    s = side(road.axis, direction)
    lane = road.lanes - 1
    lat = road.c + road.lane_offset(lane, s)
    inner = lat - s * road.lane_w / 2

    def xy(u, v):
        return (u, v) if road.axis == 0 else (v, u)

    yaw = road.heading(1)
    for u in np.arange(u0, u0 + zlen, 2.7):
        _static(layout, shapes.barrier(rng), xy(u, inner + s * 0.4), yaw)
    upstream, step = (u0 - 2.0, -2.5) if direction > 0 else (u0 + zlen + 2.0, 2.5)
    for k in range(6):
        _static(layout, shapes.traffic_cone(rng), xy(upstream + step * k, inner + s * road.lane_w * k / 7), 0.0)
    machine = shapes.construction_vehicle(rng)
    u_m = u0 + zlen / 2
    _static(layout, machine, xy(u_m, lat + s * 0.3), yaw + np.pi * (rng.random() < 0.5), "vehicle")
    for _ in range(int(rng.integers(1, 4))):
        u = u0 + rng.uniform(1, zlen - 1)
        if abs(u - u_m) > machine.wlh[1] / 2 + 1.5:
            _static(layout, shapes.pedestrian(rng, "construction_worker"), xy(u, lat + s * rng.uniform(-0.6, 0.8)),
                    rng.uniform(-np.pi, np.pi), "pedestrian")


VEHICLE_MIX = (("car", 0.60), ("truck", 0.09), ("bus", 0.07), ("semi", 0.06), ("motorcycle", 0.08),
               ("construction", 0.03), ("bicycle", 0.07))


def _vehicle_shapes(rng, kind):
    """[(Shape, lag behind the lead's bottom centre)], one or two (tractor + trailer)."""
    if kind == "car":
        return [(shapes.car(rng), 0.0)]
    if kind == "truck":
        return [(shapes.truck(rng), 0.0)]
    if kind == "bus":
        return [(shapes.bus(rng), 0.0)]
    if kind == "semi":
        tractor = shapes.truck(rng, tractor=True)
        trl = shapes.trailer(rng)
        return [(tractor, 0.0), (trl, tractor.wlh[1] / 2 + trl.wlh[1] / 2 - 1.2)]
    if kind == "motorcycle":
        return [(shapes.motorcycle(rng), 0.0)]
    if kind == "construction":
        return [(shapes.construction_vehicle(rng), 0.0)]
    return [(shapes.bicycle(rng), 0.0)]


def _turn_pieces(road_in: Road, direction, lane, cross: Road, turn, lane_out, start_u, length_after):
    """Path pieces from ``start_u`` along ``road_in`` (heading ``direction``, lane ``lane``)
    turning ``turn`` (-1 right, +1 left) into ``cross``; returns (start_xy, yaw, pieces)."""
    s_in = side(road_in.axis, direction)
    off_in = abs(road_in.lane_offset(lane, s_in))
    out_dir = direction * turn if road_in.axis == 0 else -direction * turn
    s_out = side(cross.axis, out_dir)
    off_out = abs(cross.lane_offset(lane_out, s_out))
    # canonical frame: heading +x, intersection centre at the origin; right turn exits at
    # x = -off_out heading -y, left turn at x = +off_out heading +y
    if turn < 0:
        radius = max(cross.half(-direction) - off_out + 1.0, 4.0)
        x_s = -off_out - radius
    else:
        radius = max(off_in + off_out, 6.0)
        x_s = off_out - radius
    u_c = cross.c                               # intersection position along road_in
    dist = direction * (u_c - start_u) + x_s    # distance before the arc
    pieces = [("line", max(dist, 0.1)), ("arc", radius, turn * np.pi / 2), ("line", length_after)]
    lat = road_in.c + road_in.lane_offset(lane, s_in)
    start_xy = (start_u, lat) if road_in.axis == 0 else (lat, start_u)
    return start_xy, road_in.heading(direction), pieces, dist


def _lane_path(road: Road, direction, lane, start_u, length, lateral=0.0):
    s = side(road.axis, direction)
    lat = road.c + road.lane_offset(lane, s) + s * lateral
    xy = (start_u, lat) if road.axis == 0 else (lat, start_u)
    return Path(xy, road.heading(direction), [("line", length)])


def _circles(shape_wlh, xy, yaw):
    """Footprint discs [..., k, 2] and radius of boxes at poses xy [..., 2], yaw [...]."""
    w, l = shape_wlh[0], shape_wlh[1]
    k = max(1, int(np.ceil(l / w)))
    offs = (np.arange(k) + 0.5) / k * l - l / 2
    c = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    centres = xy[..., None, :] + offs[:, None] * c[..., None, :]
    radius = np.hypot(w / 2, l / (2 * k))
    return centres, radius


def _resolve_collisions(layout: Layout, ego_path, ego_speed, duration, ego_wlh=(1.85, 4.6)):
    """Drop things (and their towed partners) that would overlap the ego, a static obstacle
    or a thing kept earlier, at any time of the scene. Returns the kept things."""
    times = np.arange(0, duration + 1e-9, 0.25)
    ego = Movers([ego_path], [ego_speed], [0.0])
    poses = [ego.pose(t) for t in times]
    ego_yaw = np.array([p[1][0] for p in poses])
    # base_link is the rear axle; the car's centre is ~1.4 m ahead
    ego_xy = np.array([p[0][0] for p in poses]) + 1.4 * np.stack([np.cos(ego_yaw), np.sin(ego_yaw)], -1)
    c, r = _circles(ego_wlh, ego_xy, ego_yaw)
    kept = [(c, np.full(c.shape[1], r))]
    if layout.obstacles:
        obs = np.array(layout.obstacles)
        for o in obs:
            kept.append((np.broadcast_to(o[None, None, :2], (len(times), 1, 2)), o[2:3]))
    everyone = Movers([t[1] for t in layout.things], [t[2] for t in layout.things], [t[3] for t in layout.things])
    all_poses = [everyone.pose(t) for t in times]
    xy_all = np.stack([p[0] for p in all_poses], 1)    # [N, T, 2]
    yaw_all = np.stack([p[1] for p in all_poses], 1)   # [N, T]
    groups = {}
    for i, th in enumerate(layout.things):
        groups.setdefault(th[5] if th[5] is not None else ("solo", i), []).append(i)

    def bbox(cc, rr):
        return np.concatenate([cc.reshape(-1, 2).min(0) - rr.max(), cc.reshape(-1, 2).max(0) + rr.max()])

    kept_box = np.array([bbox(cc, rr) for cc, rr in kept])
    keep = []
    for members in groups.values():
        cs, rs = [], []
        for i in members:
            cc, rr = _circles(layout.things[i][0].wlh, xy_all[i], yaw_all[i])
            cs.append(cc)
            rs.append(np.full(cc.shape[1], rr))
        cand_c, cand_r = np.concatenate(cs, 1), np.concatenate(rs)
        box = bbox(cand_c, cand_r)
        overlap = np.flatnonzero((kept_box[:, 0] < box[2] + 0.3) & (kept_box[:, 2] > box[0] - 0.3)
                                 & (kept_box[:, 1] < box[3] + 0.3) & (kept_box[:, 3] > box[1] - 0.3))
        hit = False
        for k in overlap:
            kc, kr = kept[k]
            d = np.linalg.norm(cand_c[:, :, None, :] - kc[:, None, :, :], axis=-1)
            if np.any(d < cand_r[None, :, None] + kr[None, None, :] + 0.3):
                hit = True
                break
        if hit:
            continue
        keep.extend(members)
        kept.append((cand_c, cand_r))
        kept_box = np.concatenate([kept_box, box[None]])
    return [layout.things[i] for i in sorted(keep)]


def build_world(seed_seq: np.random.SeedSequence, name: str, duration: float) -> World:
    """Generate one scene of ``duration`` seconds, deterministic for ``seed_seq``."""
    rng = np.random.default_rng(seed_seq)
    # -- ego motion first: it decides how big the city must be --------------------------------
    v_cruise = rng.uniform(4.0, 10.0)
    ego_speed = speed_profile(rng, duration + 1.0, rng.uniform(0, v_cruise), v_cruise, 12.0,
                              stop_prob=0.15, accel=1.8)
    travel = float(np.sum(ego_speed) * 0.02) + 5.0
    main = _random_road(rng, 0, 0.0, main=True)
    turn = int(rng.choice([0, 0, -1, 1]))
    margin = 110.0
    x0, x1 = -margin, travel + margin
    v_pos = _road_positions(rng, x0, x1, (55.0, 110.0), anchor=rng.uniform(20, 60))
    turn_road = None
    if turn:
        cands = [x for x in v_pos if 0.25 * travel + 15 < x < 0.65 * travel + 15]
        if cands:
            turn_road = float(cands[0])
    y_ext = margin + (travel if turn_road is not None else 0.0)
    y0, y1 = -y_ext, y_ext
    h_pos = _road_positions(rng, y0, y1, (60.0, 100.0), anchor=0.0)
    h_roads = [main if abs(y) < 1e-9 else _random_road(rng, 0, y) for y in h_pos]
    v_roads = [_random_road(rng, 1, x) for x in v_pos]
    for r in h_roads:
        r.lo, r.hi = x0 - 40, x1 + 40
    for r in v_roads:
        r.lo, r.hi = y0 - 40, y1 + 40
    layout = Layout(h_roads, v_roads, x0, x1, y0, y1)
    ground = GroundMap(x0 - 40, y0 - 40, x1 + 40, y1 + 40, res=0.1)

    # -- ego route ------------------------------------------------------------------------------
    ego_lane = int(rng.integers(main.lanes))
    if turn_road is not None:
        cross = next(r for r in v_roads if r.c == turn_road)
        lane_out = ego_lane if turn > 0 else cross.lanes - 1
        lane_out = min(lane_out, cross.lanes - 1)
        start_xy, yaw, pieces, _ = _turn_pieces(main, 1, ego_lane, cross, turn, lane_out, 0.0, travel + 50)
        ego_path = Path(start_xy, yaw, pieces)
    else:
        ego_path = _lane_path(main, 1, ego_lane, 0.0, travel + 50)
    route = ego_path.xy[:: max(1, len(ego_path.xy) // 400)]

    def near(x, y, dist=95.0):
        return bool(np.min(np.hypot(route[:, 0] - x, route[:, 1] - y)) < dist)

    # -- ground: blocks, sidewalks, roads, intersections, paint --------------------------------
    xs = [x0 - 40] + [r.c for r in v_roads] + [x1 + 40]
    ys = [y0 - 40] + [r.c for r in h_roads] + [y1 + 40]
    vr = {r.c: r for r in v_roads}
    hr = {r.c: r for r in h_roads}
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
    for road in h_roads + v_roads:
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
    for road in h_roads + v_roads:
        _paint_road(ground, road, rng)
    inter = [(h, v) for h in h_roads for v in v_roads]
    for h, v in inter:
        bx = _intersection_box(h, v)
        ground.fill(*bx, M.ASPHALT)
        ground.paint[ground.cells(*_intersection_box(h, v, margin=5.0))] = NO_PAINT
        ground.paint[ground.cells(*bx)] = NO_PAINT
    for h, v in inter:
        if near(v.c, h.c, 150.0):
            _crosswalks(ground, h, v)

    # -- furniture, traffic lights, barrier medians ------------------------------------------
    for road in h_roads + v_roads:
        crossing = v_roads if road.axis == 0 else h_roads
        spans = [(c.c - c.half(-1) - 5, c.c + c.half(1)) for c in crossing]
        _sidewalk_furniture(layout, rng, road, spans, near)
        if road.median_kind == "barrier":
            u = road.lo
            while u < road.hi:
                shape = shapes.barrier(rng)
                xx, yy = (u, road.c) if road.axis == 0 else (road.c, u)
                if near(xx, yy, 80.0) and not any(lo - 2 < u < hi + 6 for lo, hi in spans):
                    layout.things.append((shape, Path((xx, yy), road.heading(1), [("line", 0.01)]),
                                          np.zeros(2), 0.0, "static", None))
                u += shape.wlh[1] + 0.2
    for h, v in inter:
        if not near(v.c, h.c, 120.0):
            continue
        for sx in (-1, 1):
            for sy in (-1, 1):
                px = v.c + sx * (v.half(sx) + 0.8)
                py = h.c + sy * (h.half(sy) + 0.8)
                if rng.random() < 0.8:
                    arm = (0.0, -sy) if rng.random() < 0.5 else None
                    traffic_light(layout, rng, px, py, np.arctan2(-sy, -sx), arm, h.lanes * h.lane_w * 0.8)

    # -- construction zones: a closed outer lane with barriers, a cone taper, a machine, workers -----
    if rng.random() < 0.7:
        # on the main road's opposite carriageway (the ego keeps its lane) somewhere ahead
        free = [u for u in np.arange(-20, travel + 60, 4.0)
                if all(abs(w - v.c) > v.half(1) + 14 for v in v_roads for w in (u - 10, u + 45))]
        if free:
            _construction_zone(layout, rng, main, -1, float(rng.choice(free)), rng.uniform(18, 35))
    crossing_near = [v for v in v_roads if near(v.c, 0.0, 60.0)]
    if crossing_near and rng.random() < 0.5:
        road = crossing_near[int(rng.integers(len(crossing_near)))]
        end = int(rng.choice([-1, 1]))
        u0 = main.c + end * (main.half(end) + rng.uniform(12, 20))
        _construction_zone(layout, rng, road, int(rng.choice([-1, 1])), u0 if end > 0 else u0 - 30, 25.0)
    for road in h_roads + v_roads:  # loose cones on parking lanes / road edges
        for _ in range(int(rng.poisson(2.0))):
            u = rng.uniform(road.lo, road.hi)
            s_side = int(rng.choice([-1, 1]))
            lat = road.c + s_side * (road.half(s_side) - 0.5)
            xy = (u, lat) if road.axis == 0 else (lat, u)
            if not near(*xy, dist=70.0):
                continue
            for k in range(int(rng.integers(1, 5))):
                off = (k * 1.3, 0.0) if road.axis == 0 else (0.0, k * 1.3)
                layout.things.append((shapes.traffic_cone(rng), Path((xy[0] + off[0], xy[1] + off[1]), 0.0,
                                      [("line", 0.01)]), np.zeros(2), 0.0, "static", None))

    # -- moving traffic ---------------------------------------------------------------------------
    span = duration + 1.0
    group_id = 0
    kinds, probs = zip(*VEHICLE_MIX)
    for road in h_roads + v_roads:
        for direction in (-1, 1):
            for lane in range(road.lanes):
                u = road.lo + rng.uniform(0, 20)
                while u < road.hi:
                    u += rng.uniform(12, 50)
                    xy = (u, road.c) if road.axis == 0 else (road.c, u)
                    if not near(*xy, dist=120.0):
                        continue
                    kind = str(rng.choice(kinds, p=np.array(probs) / sum(probs)))
                    if kind == "bicycle":  # cyclists keep to the outer lane, near the curb
                        lane_k = road.lanes - 1
                    else:
                        lane_k = lane
                    v_max = {"car": 14, "truck": 11, "bus": 10, "semi": 10, "motorcycle": 16, "construction": 6,
                             "bicycle": 6}[kind]
                    cruise = rng.uniform(0.45, 1.0) * v_max
                    v0 = 0.0 if rng.random() < 0.15 else cruise * rng.uniform(0.5, 1.0)
                    speeds = speed_profile(rng, span, v0, cruise, v_max, stop_prob=0.1)
                    start_u = u
                    crossing = v_roads if road.axis == 0 else h_roads
                    ahead = [c for c in crossing if 15 < direction * (c.c - start_u) < 120]
                    members = _vehicle_shapes(rng, kind)
                    lateral = 1.0 if kind == "bicycle" else rng.uniform(-0.25, 0.25)
                    if ahead and rng.random() < 0.3 and kind not in ("semi", "bicycle"):
                        cross = ahead[0] if direction > 0 else ahead[-1]
                        t_dir = int(rng.choice([-1, 1]))
                        lane_out = min(lane_k, cross.lanes - 1) if t_dir > 0 else cross.lanes - 1
                        sxy, yaw, pieces, _ = _turn_pieces(road, direction, lane_k, cross, t_dir, lane_out,
                                                           start_u, 300)
                        path = Path(sxy, yaw, pieces)
                    else:
                        path = _lane_path(road, direction, lane_k, start_u - direction * 30, 500, lateral)
                    s_start = 0.0 if path.length < 400 else 30.0
                    gid = None
                    if len(members) > 1:
                        gid = group_id = group_id + 1
                    for shape, lag in members:
                        cycle = shape.category in ("vehicle.bicycle", "vehicle.motorcycle")
                        kind_attr = "cycle" if cycle else "vehicle"
                        layout.things.append((shape, path, speeds, s_start - lag, kind_attr, gid))
                    u += sum(m[0].wlh[1] for m in members)
            # parked cars along parking lanes
            s = side(road.axis, direction)
            pw = road.park[(s + 1) // 2]
            if pw > 0:
                lat = road.c + s * (road.median / 2 + road.lanes * road.lane_w + pw / 2)
                u = road.lo
                while u < road.hi:
                    u += rng.uniform(5.6, 7.0)
                    xy = (u, lat) if road.axis == 0 else (lat, u)
                    if not near(*xy, dist=110.0) or rng.random() < 0.35:
                        continue
                    shape = shapes.car(rng) if rng.random() < 0.93 else shapes.truck(rng)
                    if shape.category == "vehicle.truck":
                        u += shape.wlh[1] - 4
                    layout.things.append((shape, Path(xy, road.heading(direction), [("line", 0.01)]),
                                          np.zeros(2), 0.0, "vehicle", None))

    # -- pedestrians on sidewalks and crosswalks -------------------------------------------------
    for road in h_roads + v_roads:
        for s in (-1, 1):
            curb = road.c + s * road.half(s)
            u = road.lo
            while u < road.hi:
                u += rng.exponential(14.0)
                lat = curb + s * rng.uniform(2.2, max(road.sidewalk - 0.5, 2.3))
                xy = (u, lat) if road.axis == 0 else (lat, u)
                if not near(*xy, dist=100.0):
                    continue
                kind = "child" if rng.random() < 0.08 else "adult"
                shape = shapes.pedestrian(rng, kind)
                direction = int(rng.choice([-1, 1]))
                standing = rng.random() < 0.25
                speeds = np.zeros(2) if standing else speed_profile(rng, span, 1.3, rng.uniform(0.8, 1.7), 2.0,
                                                                        change_every=(2, 6), accel=0.8, stop_prob=0.1)
                path = Path(xy, road.heading(direction), [("line", 0.01 if standing else 200)])
                layout.things.append((shape, path, speeds, 0.0, "pedestrian", None))
    for h, v in inter:
        if not near(v.c, h.c, 90.0):
            continue
        for _ in range(int(rng.integers(0, 4))):
            road, cross = (h, v) if rng.random() < 0.5 else (v, h)
            end = int(rng.choice([-1, 1]))
            u = cross.c + end * (cross.half(end) + 2.5)
            direction = int(rng.choice([-1, 1]))
            start_lat = road.c - direction * (road.half(-direction) + 1.2)
            xy = (u, start_lat) if road.axis == 0 else (start_lat, u)
            across_x = np.pi / 2 if direction > 0 else -np.pi / 2
            heading = across_x if road.axis == 0 else (0.0 if direction > 0 else np.pi)
            walk = road.half(-1) + road.half(1) + 4
            wait = rng.uniform(0, duration)
            sp = np.concatenate([np.zeros(int(wait / 0.02)), speed_profile(rng, span, 1.2, 1.4, 1.8)])
            layout.things.append((shapes.pedestrian(rng), Path(xy, heading, [("line", walk)]), sp, 0.0,
                                  "pedestrian", None))

    things = _resolve_collisions(layout, ego_path, ego_speed, duration)

    # -- assemble -------------------------------------------------------------------------------
    movers = Movers([t[1] for t in things], [t[2] for t in things], [t[3] for t in things])
    thing_list = [Thing(t[0], i, t[4]) for i, t in enumerate(things)]
    ego = Movers([ego_path], [ego_speed], [0.0])
    sun_el = np.deg2rad(rng.uniform(12, 65))
    sun_az = rng.uniform(-np.pi, np.pi)
    cloud = float(rng.choice([0.0, 0.2, 0.5, 0.9]))
    sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    warm = rng.uniform(0.0, 0.25) * (1 - np.sin(sun_el))
    lighting = Lighting(
        sun=sun, sun_color=(1 - 0.8 * cloud) * np.array([1.0, 0.95 - warm * 0.3, 0.88 - warm]) * 1.1,
        ambient=np.array([0.42, 0.46, 0.55]) * (0.7 + 0.6 * cloud),
        zenith=np.array([0.25, 0.45, 0.85]) * (1 - cloud) + np.array([0.6, 0.62, 0.66]) * cloud,
        horizon=np.array([0.75, 0.82, 0.92]) * (1 - cloud) + np.array([0.78, 0.78, 0.8]) * cloud,
        fog_distance=float(rng.uniform(180, 600) * (1 - 0.5 * cloud)), exposure=float(rng.uniform(0.85, 1.15)),
        cloudiness=cloud)
    theta = rng.uniform(-np.pi, np.pi)
    offset = rng.uniform(300, 1800, size=2)
    static = Primitives.concat(layout.static)
    return World(name, duration, theta, offset, ground, static, thing_list, movers, ego, lighting,
                 texture_seed=int(rng.integers(1 << 30)))
