"""The ego's motion: its speed over the scene, its route through the road grid, and which
points are within sight of that route (the city is only furnished there)."""
from __future__ import annotations

import numpy as np

from ..motion import Path, speed_profile
from .road_grid import Layout, lane_path, turn_pieces


def ego_speed_profile(rng, duration):
    """(speeds, travel): the ego's speed profile and the distance (metres, with a few to
    spare) it covers in ``duration`` seconds."""
    v_cruise = rng.uniform(4.0, 10.0)
    ego_speed = speed_profile(rng, duration + 1.0, rng.uniform(0, v_cruise), v_cruise, 12.0,
                              stop_prob=0.15, accel=1.8)
    travel = float(np.sum(ego_speed) * 0.02) + 5.0
    return ego_speed, travel


def ego_route(rng, layout: Layout, turn, turn_at, travel):
    """The ego's path: along a lane of the main road heading +x, turning ``turn`` into the
    road along y at x = ``turn_at`` unless that is None (see ``plan_roads``)."""
    main = layout.main
    ego_lane = int(rng.integers(main.lanes))
    if turn_at is not None:
        cross = next(r for r in layout.v_roads if r.c == turn_at)
        lane_out = ego_lane if turn > 0 else cross.lanes - 1
        lane_out = min(lane_out, cross.lanes - 1)
        start_xy, yaw, pieces, _ = turn_pieces(main, 1, ego_lane, cross, turn, lane_out, 0.0, travel + 50)
        return Path(start_xy, yaw, pieces)
    return lane_path(main, 1, ego_lane, 0.0, travel + 50)


class NearRoute:
    """``near(x, y, dist)``: whether the city-frame point (x, y) lies within ``dist`` metres of
    the ego's route (about 400 of its path samples)."""

    def __init__(self, ego_path: Path):
        self.route = ego_path.xy[:: max(1, len(ego_path.xy) // 400)]

    def __call__(self, x, y, dist=95.0):
        return bool(np.min(np.hypot(self.route[:, 0] - x, self.route[:, 1] - y)) < dist)
