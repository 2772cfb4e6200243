"""The road grid of one scene in the city frame, and paths along its lanes.

Right-hand traffic. A road along x (axis 0) or y (axis 1) has ``lanes`` lanes per
direction; lane i (0 = next to the centre) of the direction ``d`` (+1 / -1 along the axis)
lies on side ``side(axis, d)`` of the centre line.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..motion import Path

BORDER = 40.0   # metres the roads and the ground map reach past the layout's area


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
    main: Road | None = None                         # the road the ego starts on (y = 0)
    static: list = field(default_factory=list)       # Primitives (stuff)
    things: list = field(default_factory=list)       # (Shape, Path, speeds, s0, kind, group)
    obstacles: list = field(default_factory=list)    # (x, y, radius) static no-go discs

    @property
    def roads(self):
        return self.h_roads + self.v_roads

    def intersections(self):
        """(h, v) for every crossing of a road along x with a road along y."""
        return [(h, v) for h in self.h_roads for v in self.v_roads]


def random_road(rng, axis, c, main=False):
    lanes = int(rng.choice([1, 2, 2, 3] if main else [1, 1, 2]))
    lane_w = rng.uniform(3.1, 3.6)
    median_kind = str(rng.choice(["paint", "paint", "raised", "grass", "barrier"] if lanes > 1 else ["paint"]))
    median = {"paint": 0.3, "raised": rng.uniform(1.2, 2.5), "grass": rng.uniform(2.5, 5.0),
              "barrier": 0.9}[median_kind]
    park = tuple(float(rng.uniform(2.2, 2.6)) if rng.random() < 0.5 else 0.0 for _ in range(2))
    return Road(axis, float(c), lanes, float(lane_w), float(median), median_kind, park,
                float(rng.uniform(3.0, 5.5)))


def road_positions(rng, lo, hi, spacing, anchor=0.0):
    """Road centre coordinates covering [lo, hi] with random spacing, one at ``anchor``."""
    pos = [anchor]
    while pos[-1] < hi:
        pos.append(pos[-1] + rng.uniform(*spacing))
    while pos[0] > lo:
        pos.insert(0, pos[0] - rng.uniform(*spacing))
    return pos


def plan_roads(rng, travel, margin=110.0):
    """The road grid around a route of ``travel`` metres along the main road (y = 0, heading
    +x from x = 0), ``margin`` metres beyond it on every side. Returns (layout, turn, turn_at):
    the ego turns ``turn`` (-1 right, +1 left) into the road along y at x = ``turn_at``, or
    goes straight on where ``turn_at`` is None."""
    main = random_road(rng, 0, 0.0, main=True)
    turn = int(rng.choice([0, 0, -1, 1]))
    x0, x1 = -margin, travel + margin
    v_pos = road_positions(rng, x0, x1, (55.0, 110.0), anchor=rng.uniform(20, 60))
    turn_at = None
    if turn:
        cands = [x for x in v_pos if 0.25 * travel + 15 < x < 0.65 * travel + 15]
        if cands:
            turn_at = float(cands[0])
    y_ext = margin + (travel if turn_at is not None else 0.0)
    y0, y1 = -y_ext, y_ext
    h_pos = road_positions(rng, y0, y1, (60.0, 100.0), anchor=0.0)
    h_roads = [main if abs(y) < 1e-9 else random_road(rng, 0, y) for y in h_pos]
    v_roads = [random_road(rng, 1, x) for x in v_pos]
    for r in h_roads:
        r.lo, r.hi = x0 - BORDER, x1 + BORDER
    for r in v_roads:
        r.lo, r.hi = y0 - BORDER, y1 + BORDER
    return Layout(h_roads, v_roads, x0, x1, y0, y1, main=main), turn, turn_at


def plan_open_road(rng, travel, margin=110.0):
    """An open road instead of a city: the main road alone (no crossing road, no parking
    lane, a narrow verge for a walkway) through countryside. Returns (layout, 0, None) like
    ``plan_roads`` (the ego goes straight on)."""
    main = random_road(rng, 0, 0.0, main=True)
    main.park, main.sidewalk = (0.0, 0.0), float(rng.uniform(1.5, 2.5))
    x0, x1, y0, y1 = -margin, travel + margin, -margin, margin
    main.lo, main.hi = x0 - BORDER, x1 + BORDER
    return Layout([main], [], x0, x1, y0, y1, main=main), 0, None


def turn_pieces(road_in: Road, direction, lane, cross: Road, turn, lane_out, start_u, length_after):
    """Path pieces from ``start_u`` along ``road_in`` (heading ``direction``, lane ``lane``)
    turning ``turn`` (-1 right, +1 left) into ``cross``; returns (start_xy, yaw, pieces,
    distance before the arc)."""
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


def lane_path(road: Road, direction, lane, start_u, length, lateral=0.0):
    s = side(road.axis, direction)
    lat = road.c + road.lane_offset(lane, s) + s * lateral
    xy = (start_u, lat) if road.axis == 0 else (lat, start_u)
    return Path(xy, road.heading(direction), [("line", length)])
