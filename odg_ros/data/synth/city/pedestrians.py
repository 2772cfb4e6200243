"""People walking or standing on the sidewalks, and crossing at the intersections."""
from __future__ import annotations

import numpy as np

from .. import shapes
from ..motion import Path, speed_profile
from .road_grid import Layout, Road


def place_pedestrians(layout: Layout, rng, span, duration, near, density: float = 1.0):
    """Pedestrians moving for ``span`` seconds, where they can be seen from the route
    (``near``, see ego.NearRoute); the crossing ones set off at any time of the scene's
    ``duration``. ``density`` scales how many (1 draws exactly the normal city's)."""
    for road in layout.roads:
        _sidewalk_pedestrians(layout, rng, road, span, near, density)
    for h, v in layout.intersections():
        if near(v.c, h.c, 90.0):
            _crossing_pedestrians(layout, rng, h, v, span, duration, density)


def _sidewalk_pedestrians(layout: Layout, rng, road: Road, span, near, density: float):
    """Adults and a few children along both sidewalks of ``road``, a quarter of them standing."""
    for s in (-1, 1):
        curb = road.c + s * road.half(s)
        u = road.lo
        while u < road.hi:
            u += rng.exponential(14.0) / density
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


def _crossing_pedestrians(layout: Layout, rng, h: Road, v: Road, span, duration,
                          density: float):
    """Up to three people (times ``density``) who wait at a crosswalk of the intersection
    h x v, then cross."""
    for _ in range(int(round(int(rng.integers(0, 4)) * density))):
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
