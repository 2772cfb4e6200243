"""``build_world``: one scene, section by section. All sections draw from one generator, so
the order of the calls is part of every generated world."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..motion import Movers
from ..primitives import Primitives
from ..world import GroundMap, Lighting, Thing, World
from .collisions import resolve_collisions
from .ego import NearRoute, ego_route, ego_speed_profile
from .furniture import fill_blocks, fill_countryside, place_street_furniture
from .road_grid import BORDER, Layout, plan_open_road, plan_roads
from .pedestrians import place_pedestrians
from .roads import pave_roads
from .traffic import place_construction_zones, place_traffic


# how many road users a scene of each traffic class has, relative to the normal city
TRAFFIC = {"quiet": 0.3, "normal": 1.0, "dense": 2.5}
ROADS = ("city", "open-road")
# an open road has few people walking beside it, whatever its traffic
OPEN_ROAD_PEDESTRIANS = 0.15


@dataclass(frozen=True)
class SceneKind:
    """What kind of scene to build: its traffic (a TRAFFIC key) and its roads (city: the road
    grid with blocks; open-road: one road through countryside). The default is the city the
    generator always built, draw for draw."""
    traffic: str = "normal"
    roads: str = "city"

    def __post_init__(self):
        if self.traffic not in TRAFFIC:
            raise ValueError(f"traffic {self.traffic!r}: expected one of {', '.join(TRAFFIC)}")
        if self.roads not in ROADS:
            raise ValueError(f"roads {self.roads!r}: expected one of {', '.join(ROADS)}")

    @property
    def name(self) -> str:
        return f"{self.roads}-{self.traffic}"

    @property
    def description(self) -> str:
        """A few words for the scene table ("city" for the default kind)."""
        words = ["open road" if self.roads == "open-road" else "city"]
        return ", ".join(words + ([f"{self.traffic} traffic"] if self.traffic != "normal" else []))


# the held-out worlds of each scene class (docs/results/query_budget.md): class name ->
# (seed, kind) for ``odg synth --seed SEED --traffic T --roads R``; no training set uses these
# seeds, and test/data/test_synth_classes.py pins what they hold
HELD_OUT = {"city-quiet": (9101, SceneKind("quiet")),
            "city-normal": (9102, SceneKind("normal")),
            "city-dense": (9103, SceneKind("dense")),
            "open-road": (9104, SceneKind("normal", "open-road"))}


def build_world(seed_seq: np.random.SeedSequence, name: str, duration: float,
                kind: SceneKind = SceneKind()) -> World:
    """Generate one scene of ``duration`` seconds and ``kind``, deterministic for
    ``seed_seq``."""
    rng = np.random.default_rng(seed_seq)
    # the ego's motion first: it decides how big the city must be
    ego_speed, travel = ego_speed_profile(rng, duration)
    open_road = kind.roads == "open-road"
    layout, turn, turn_at = (plan_open_road if open_road else plan_roads)(rng, travel)
    ego_path = ego_route(rng, layout, turn, turn_at, travel)
    near = NearRoute(ego_path)
    ground = GroundMap(layout.x0 - BORDER, layout.y0 - BORDER, layout.x1 + BORDER, layout.y1 + BORDER, res=0.1)
    (fill_countryside if open_road else fill_blocks)(layout, ground, rng, near)
    pave_roads(layout, ground, rng, near)
    place_street_furniture(layout, rng, near)
    place_construction_zones(layout, rng, travel, near)
    span = duration + 1.0
    density = TRAFFIC[kind.traffic]
    place_traffic(layout, rng, span, near, density)
    place_pedestrians(layout, rng, span, duration, near,
                      density * (OPEN_ROAD_PEDESTRIANS if open_road else 1.0))
    things = resolve_collisions(layout, ego_path, ego_speed, duration)
    return _assemble(rng, name, duration, layout, ground, things, Movers([ego_path], [ego_speed], [0.0]))


def _assemble(rng, name, duration, layout: Layout, ground, things, ego: Movers) -> World:
    """The World of the kept things, with random lighting and a random placement of the city
    in the global frame."""
    movers = Movers([t[1] for t in things], [t[2] for t in things], [t[3] for t in things])
    thing_list = [Thing(t[0], i, t[4]) for i, t in enumerate(things)]
    lighting = _random_lighting(rng)
    theta = rng.uniform(-np.pi, np.pi)
    offset = rng.uniform(300, 1800, size=2)
    static = Primitives.concat(layout.static)
    return World(name, duration, theta, offset, ground, static, thing_list, movers, ego, lighting,
                 texture_seed=int(rng.integers(1 << 30)))


def _random_lighting(rng) -> Lighting:
    """Sun direction, cloud cover (dimming the sun, greying the sky), haze and exposure."""
    sun_el = np.deg2rad(rng.uniform(12, 65))
    sun_az = rng.uniform(-np.pi, np.pi)
    cloud = float(rng.choice([0.0, 0.2, 0.5, 0.9]))
    sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    warm = rng.uniform(0.0, 0.25) * (1 - np.sin(sun_el))
    return Lighting(
        sun=sun, sun_color=(1 - 0.8 * cloud) * np.array([1.0, 0.95 - warm * 0.3, 0.88 - warm]) * 1.1,
        ambient=np.array([0.42, 0.46, 0.55]) * (0.7 + 0.6 * cloud),
        zenith=np.array([0.25, 0.45, 0.85]) * (1 - cloud) + np.array([0.6, 0.62, 0.66]) * cloud,
        horizon=np.array([0.75, 0.82, 0.92]) * (1 - cloud) + np.array([0.78, 0.78, 0.8]) * cloud,
        fog_distance=float(rng.uniform(180, 600) * (1 - 0.5 * cloud)), exposure=float(rng.uniform(0.85, 1.15)),
        cloudiness=cloud)
