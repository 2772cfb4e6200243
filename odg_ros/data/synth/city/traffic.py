"""Road users and road works: vehicles and cyclists in every lane (some turning at the next
intersection), parked cars along parking lanes, construction zones and loose cones."""
from __future__ import annotations

import itertools

import numpy as np

from .. import shapes
from ..motion import Path, speed_profile
from .road_grid import Layout, Road, lane_path, side, turn_pieces

VEHICLE_MIX = (("car", 0.60), ("truck", 0.09), ("bus", 0.07), ("semi", 0.06), ("motorcycle", 0.08),
               ("construction", 0.03), ("bicycle", 0.07))
TOP_SPEED = {"car": 14, "truck": 11, "bus": 10, "semi": 10, "motorcycle": 16, "construction": 6, "bicycle": 6}


# -- construction zones -------------------------------------------------------------------------

def place_construction_zones(layout: Layout, rng, travel, near):
    """Often a zone on the main road's opposite carriageway somewhere ahead (the ego keeps its
    lane), sometimes one on a crossing road near the start, and loose cones along road edges,
    where they can be seen from the route (``near``, see ego.NearRoute)."""
    main = layout.main
    if rng.random() < 0.7:
        free = [u for u in np.arange(-20, travel + 60, 4.0)
                if all(abs(w - v.c) > v.half(1) + 14 for v in layout.v_roads for w in (u - 10, u + 45))]
        if free:
            _construction_zone(layout, rng, main, -1, float(rng.choice(free)), rng.uniform(18, 35))
    crossing_near = [v for v in layout.v_roads if near(v.c, 0.0, 60.0)]
    if crossing_near and rng.random() < 0.5:
        road = crossing_near[int(rng.integers(len(crossing_near)))]
        end = int(rng.choice([-1, 1]))
        u0 = main.c + end * (main.half(end) + rng.uniform(12, 20))
        _construction_zone(layout, rng, road, int(rng.choice([-1, 1])), u0 if end > 0 else u0 - 30, 25.0)
    _loose_cones(layout, rng, near)


def _place_static(layout, shape, xy, yaw, kind="static"):
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
        _place_static(layout, shapes.barrier(rng), xy(u, inner + s * 0.4), yaw)
    upstream, step = (u0 - 2.0, -2.5) if direction > 0 else (u0 + zlen + 2.0, 2.5)
    for k in range(6):
        _place_static(layout, shapes.traffic_cone(rng), xy(upstream + step * k, inner + s * road.lane_w * k / 7), 0.0)
    machine = shapes.construction_vehicle(rng)
    u_m = u0 + zlen / 2
    _place_static(layout, machine, xy(u_m, lat + s * 0.3), yaw + np.pi * (rng.random() < 0.5), "vehicle")
    for _ in range(int(rng.integers(1, 4))):
        u = u0 + rng.uniform(1, zlen - 1)
        if abs(u - u_m) > machine.wlh[1] / 2 + 1.5:
            _place_static(layout, shapes.pedestrian(rng, "construction_worker"),
                          xy(u, lat + s * rng.uniform(-0.6, 0.8)), rng.uniform(-np.pi, np.pi), "pedestrian")


def _loose_cones(layout: Layout, rng, near):
    """A few rows of cones on parking lanes / road edges of every road."""
    for road in layout.roads:
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


# -- moving and parked vehicles -----------------------------------------------------------------

def place_traffic(layout: Layout, rng, span, near, density: float = 1.0):
    """Vehicles and cyclists moving in every lane for ``span`` seconds, and parked cars along
    the parking lanes, where they can be seen from the route (``near``, see ego.NearRoute).
    ``density`` scales how many (scene.TRAFFIC; 1 draws exactly the normal city's)."""
    group_ids = itertools.count(1)   # a tractor and its trailer share one
    for road in layout.roads:
        for direction in (-1, 1):
            for lane in range(road.lanes):
                u = road.lo + rng.uniform(0, 20)
                while u < road.hi:
                    u += rng.uniform(12, 50) / density
                    xy = (u, road.c) if road.axis == 0 else (road.c, u)
                    if not near(*xy, dist=120.0):
                        continue
                    u += _add_vehicle(layout, rng, road, direction, lane, u, span, group_ids)
            _parked_cars(layout, rng, road, direction, near, density)


def _add_vehicle(layout: Layout, rng, road: Road, direction, lane, start_u, span, group_ids):
    """A vehicle of a random kind at ``start_u`` along ``road`` heading ``direction`` (cyclists
    keep to the outer lane); returns the length it takes up."""
    kinds, probs = zip(*VEHICLE_MIX)
    kind = str(rng.choice(kinds, p=np.array(probs) / sum(probs)))
    lane = road.lanes - 1 if kind == "bicycle" else lane
    v_max = TOP_SPEED[kind]
    cruise = rng.uniform(0.45, 1.0) * v_max
    v0 = 0.0 if rng.random() < 0.15 else cruise * rng.uniform(0.5, 1.0)
    speeds = speed_profile(rng, span, v0, cruise, v_max, stop_prob=0.1)
    members = _vehicle_shapes(rng, kind)
    lateral = 1.0 if kind == "bicycle" else rng.uniform(-0.25, 0.25)   # cyclists ride near the curb
    path = _vehicle_path(layout, rng, road, direction, lane, kind, start_u, lateral)
    s_start = 0.0 if path.length < 400 else 30.0
    gid = next(group_ids) if len(members) > 1 else None
    for shape, lag in members:
        cycle = shape.category in ("vehicle.bicycle", "vehicle.motorcycle")
        layout.things.append((shape, path, speeds, s_start - lag, "cycle" if cycle else "vehicle", gid))
    return sum(m[0].wlh[1] for m in members)


def _vehicle_path(layout: Layout, rng, road: Road, direction, lane, kind, start_u, lateral):
    """Sometimes a turn at one of the next intersections, else straight along the lane from
    30 m behind ``start_u``."""
    crossing = layout.v_roads if road.axis == 0 else layout.h_roads
    ahead = [c for c in crossing if 15 < direction * (c.c - start_u) < 120]
    if ahead and rng.random() < 0.3 and kind not in ("semi", "bicycle"):
        cross = ahead[0] if direction > 0 else ahead[-1]
        t_dir = int(rng.choice([-1, 1]))
        lane_out = min(lane, cross.lanes - 1) if t_dir > 0 else cross.lanes - 1
        sxy, yaw, pieces, _ = turn_pieces(road, direction, lane, cross, t_dir, lane_out, start_u, 300)
        return Path(sxy, yaw, pieces)
    return lane_path(road, direction, lane, start_u - direction * 30, 500, lateral)


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


def _parked_cars(layout: Layout, rng, road: Road, direction, near, density: float):
    """Cars (and a few trucks) along the parking lane on the side of ``direction``, if any:
    35 % of the places free at density 1, fewer above, more below."""
    s = side(road.axis, direction)
    pw = road.park[(s + 1) // 2]
    if pw <= 0:
        return
    lat = road.c + s * (road.median / 2 + road.lanes * road.lane_w + pw / 2)
    u = road.lo
    while u < road.hi:
        u += rng.uniform(5.6, 7.0)
        xy = (u, lat) if road.axis == 0 else (lat, u)
        if not near(*xy, dist=110.0) or rng.random() < 1.0 - min(1.0, 0.65 * density):
            continue
        shape = shapes.car(rng) if rng.random() < 0.93 else shapes.truck(rng)
        if shape.category == "vehicle.truck":
            u += shape.wlh[1] - 4
        layout.things.append((shape, Path(xy, road.heading(direction), [("line", 0.01)]),
                              np.zeros(2), 0.0, "vehicle", None))
