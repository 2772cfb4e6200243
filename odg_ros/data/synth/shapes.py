"""Shapes of the annotated objects (vehicles, people, barriers, cones, ...) as primitives in
the object's local frame: origin at the bottom centre of its 3D box, x along the length
(heading), y to the left, z up. Every part lies inside the box [-l/2, l/2] x [-w/2, w/2] x
[0, h], so the annotated box contains the object's voxels. Riders are part of their
bicycle/motorcycle (box and labels), as in the nuScenes boxes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...classes import OCC_CLASSES
from ..lidarseg import lidarseg_index
from . import materials as M
from .primitives import BOX, ELLIPSOID, FRUSTUM, Primitives, make

CATEGORY_TO_OCC = {
    "vehicle.car": "car", "vehicle.truck": "truck", "vehicle.bus.rigid": "bus",
    "vehicle.trailer": "trailer", "vehicle.construction": "construction_vehicle",
    "vehicle.motorcycle": "motorcycle", "vehicle.bicycle": "bicycle",
    "human.pedestrian.adult": "pedestrian", "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian",
    "movable_object.barrier": "barrier", "movable_object.trafficcone": "traffic_cone",
    "movable_object.pushable_pullable": "others", "static_object.bicycle_rack": "others",
}

CAR_COLORS = ((0.75, 0.75, 0.76), (0.08, 0.08, 0.09), (0.55, 0.56, 0.58), (0.9, 0.9, 0.88),
              (0.45, 0.05, 0.05), (0.08, 0.15, 0.38), (0.2, 0.3, 0.22), (0.6, 0.5, 0.35),
              (0.85, 0.6, 0.1), (0.3, 0.3, 0.32))
CLOTH_COLORS = ((0.1, 0.1, 0.12), (0.2, 0.25, 0.45), (0.5, 0.1, 0.1), (0.6, 0.6, 0.6),
                (0.35, 0.25, 0.15), (0.15, 0.35, 0.2), (0.8, 0.75, 0.6), (0.45, 0.2, 0.45))
SKIN_COLORS = ((0.87, 0.7, 0.58), (0.62, 0.45, 0.33), (0.4, 0.27, 0.2), (0.95, 0.8, 0.7))


@dataclass
class Shape:
    category: str          # nuScenes category name
    wlh: tuple             # box size (width, length, height), metres
    parts: Primitives      # local frame
    attribute: str = ""    # default nuScenes attribute name ("" = none)


class _Builder:
    def __init__(self, category):
        self.label = OCC_CLASSES.index(CATEGORY_TO_OCC[category])
        self.seg = lidarseg_index(category)
        self.parts = []

    def add(self, kind, center, half, material, color, yaw=0.0, taper=1.0):
        self.parts.append(make(kind, center, half, yaw, self.label, self.seg, material, color, taper=taper))

    def box(self, x0, x1, y0, y1, z0, z1, material, color):
        self.add(BOX, ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2),
                 ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2), material, color)

    def wheel(self, x, y, radius, half_width):
        self.add(ELLIPSOID, (x, y, radius), (radius, half_width, radius), M.TYRE, (0.06, 0.06, 0.06))

    def done(self):
        return Primitives.concat(self.parts)


def _pick(rng, options):
    return np.asarray(options[rng.integers(len(options))], dtype=np.float32)


def car(rng) -> Shape:
    w, l, h = rng.uniform(1.75, 2.0), rng.uniform(4.0, 4.9), rng.uniform(1.45, 1.85)
    color = _pick(rng, CAR_COLORS)
    b = _Builder("vehicle.car")
    r = rng.uniform(0.3, 0.36)
    belt = h * rng.uniform(0.55, 0.62)
    b.box(-l / 2, l / 2, -w / 2, w / 2, 0.22, belt, M.PAINT, color)
    front = rng.uniform(0.05, 0.22) * l
    b.box(-l / 2 + 0.08 * l, l / 2 - front - 0.1 * l, -0.44 * w, 0.44 * w, belt, h, M.GLASS, color)
    for x in (l / 2 - 0.18 * l, -l / 2 + 0.2 * l):
        for y in (w / 2 - 0.13, -w / 2 + 0.13):
            b.wheel(x, y, r, 0.12)
    return Shape("vehicle.car", (w, l, h), b.done())


def truck(rng, tractor=False) -> Shape:
    w, h = rng.uniform(2.3, 2.55), rng.uniform(2.9, 3.6)
    l = rng.uniform(5.5, 6.5) if tractor else rng.uniform(6.5, 9.5)
    color = _pick(rng, CAR_COLORS)
    b = _Builder("vehicle.truck")
    cab = 2.2
    cab_h = min(h, 3.0) if tractor else h * 0.8
    b.box(l / 2 - cab, l / 2, -w / 2, w / 2, 0.5, cab_h * 0.6, M.PAINT, color)
    b.box(l / 2 - cab, l / 2 - 0.05, -w / 2 + 0.05, w / 2 - 0.05, cab_h * 0.6, cab_h, M.GLASS, color)
    b.box(-l / 2, l / 2 - cab, -0.4 * w, 0.4 * w, 0.45, 0.95, M.METAL, (0.15, 0.15, 0.15))
    if not tractor:
        cargo = _pick(rng, ((0.92, 0.92, 0.9), (0.7, 0.1, 0.1), (0.2, 0.3, 0.6), (0.85, 0.85, 0.8)))
        b.box(-l / 2, l / 2 - cab - 0.3, -w / 2, w / 2, 0.95, h, M.CARGO, cargo)
    r = 0.5
    for x in (l / 2 - 1.2, -l / 2 + 1.0, -l / 2 + 2.3):
        for y in (w / 2 - 0.16, -w / 2 + 0.16):
            b.wheel(x, y, r, 0.15)
    return Shape("vehicle.truck", (w, l, h), b.done())


def bus(rng) -> Shape:
    w, l, h = rng.uniform(2.5, 2.9), rng.uniform(10.0, 12.5), rng.uniform(3.0, 3.4)
    color = _pick(rng, ((0.9, 0.75, 0.1), (0.85, 0.1, 0.1), (0.1, 0.35, 0.7), (0.92, 0.92, 0.92)))
    b = _Builder("vehicle.bus.rigid")
    b.box(-l / 2, l / 2, -w / 2, w / 2, 0.32, h, M.BUS_BODY, color)
    for x in (l / 2 - 2.5, -l / 2 + 2.8):
        for y in (w / 2 - 0.16, -w / 2 + 0.16):
            b.wheel(x, y, 0.5, 0.15)
    return Shape("vehicle.bus.rigid", (w, l, h), b.done())


def trailer(rng) -> Shape:
    w, l, h = rng.uniform(2.45, 2.6), rng.uniform(7.5, 12.0), rng.uniform(3.6, 4.0)
    b = _Builder("vehicle.trailer")
    cargo = _pick(rng, ((0.9, 0.9, 0.9), (0.6, 0.62, 0.65), (0.2, 0.4, 0.3)))
    b.box(-l / 2, l / 2, -w / 2, w / 2, 1.15, h, M.CARGO, cargo)
    b.box(l / 2 - 1.6, l / 2 - 1.4, -0.8, 0.8, 0.0, 1.15, M.METAL, (0.2, 0.2, 0.2))
    for x in (-l / 2 + 1.0, -l / 2 + 2.2):
        for y in (w / 2 - 0.16, -w / 2 + 0.16):
            b.wheel(x, y, 0.5, 0.15)
    return Shape("vehicle.trailer", (w, l, h), b.done())


def construction_vehicle(rng) -> Shape:
    w, l, h = rng.uniform(2.5, 3.0), rng.uniform(5.5, 7.5), rng.uniform(3.0, 3.8)
    color = _pick(rng, ((0.95, 0.7, 0.05), (0.95, 0.45, 0.05), (0.9, 0.85, 0.2)))
    b = _Builder("vehicle.construction")
    for y in (w / 2 - 0.3, -w / 2 + 0.3):
        b.box(-l / 2 + 0.3, l / 2 - 1.6, y - 0.3, y + 0.3, 0.0, 0.75, M.TYRE, (0.08, 0.08, 0.08))
    b.box(-l / 2, l / 2 - 1.8, -w / 2 + 0.1, w / 2 - 0.1, 0.75, 1.7, M.HAZARD, color)
    b.box(-l / 2 + 0.4, -l / 2 + 2.2, -w / 2 + 0.2, 0.3, 1.7, h, M.GLASS, color)
    b.box(-l / 2 + 2.0, l / 2 - 0.6, 0.4, 0.9, 1.9, 2.4, M.HAZARD, color)
    b.box(l / 2 - 1.2, l / 2, -w / 2 + 0.1, w / 2 - 0.1, 0.05, 0.9, M.METAL, (0.25, 0.25, 0.25))
    return Shape("vehicle.construction", (w, l, h), b.done())


def _rider(b, rng, x, h, torso_z0, helmet):
    b.add(ELLIPSOID, (x, 0, (torso_z0 + h - 0.26) / 2), (0.2, 0.2, (h - 0.26 - torso_z0) / 2), M.CLOTH,
          _pick(rng, CLOTH_COLORS))
    b.add(ELLIPSOID, (x + 0.05, 0, h - 0.13), (0.13, 0.12, 0.13), M.PAINT if helmet else M.SKIN,
          (0.1, 0.1, 0.1) if helmet else _pick(rng, SKIN_COLORS))


def motorcycle(rng) -> Shape:
    w, l, h = rng.uniform(0.7, 0.9), rng.uniform(1.9, 2.3), rng.uniform(1.4, 1.6)
    b = _Builder("vehicle.motorcycle")
    for x in (l / 2 - 0.32, -l / 2 + 0.32):
        b.wheel(x, 0, 0.31, 0.07)
    b.box(-l / 2 + 0.35, l / 2 - 0.4, -0.18, 0.18, 0.35, 0.85, M.PAINT, _pick(rng, CAR_COLORS))
    _rider(b, rng, -0.15, h, 0.8, helmet=True)
    return Shape("vehicle.motorcycle", (w, l, h), b.done(), "cycle.with_rider")


def bicycle(rng, rider=True) -> Shape:
    w, l = rng.uniform(0.5, 0.7), rng.uniform(1.6, 1.8)
    h = rng.uniform(1.55, 1.8) if rider else 1.05
    b = _Builder("vehicle.bicycle")
    for x in (l / 2 - 0.34, -l / 2 + 0.34):
        b.wheel(x, 0, 0.34, 0.04)
    b.box(-l / 2 + 0.35, l / 2 - 0.35, -0.04, 0.04, 0.45, 0.9, M.METAL, _pick(rng, CAR_COLORS))
    if rider:
        b.box(-0.25, 0.15, -0.15, 0.15, 0.45, 0.95, M.CLOTH, _pick(rng, CLOTH_COLORS))
        _rider(b, rng, -0.1, h, 0.9, helmet=bool(rng.random() < 0.5))
    return Shape("vehicle.bicycle", (w, l, h), b.done(), "cycle.with_rider" if rider else "cycle.without_rider")


def pedestrian(rng, kind="adult") -> Shape:
    category = f"human.pedestrian.{kind}"
    h = rng.uniform(1.0, 1.35) if kind == "child" else rng.uniform(1.55, 1.92)
    w, l = rng.uniform(0.5, 0.75) * (0.75 if kind == "child" else 1), rng.uniform(0.45, 0.75)
    b = _Builder(category)
    legs = _pick(rng, CLOTH_COLORS)
    top = np.array((0.95, 0.55, 0.05), np.float32) if kind == "construction_worker" else _pick(rng, CLOTH_COLORS)
    b.box(-0.12, 0.12, -0.3 * w, 0.3 * w, 0.0, 0.47 * h, M.CLOTH, legs)
    b.add(ELLIPSOID, (0, 0, 0.64 * h), (0.13, 0.45 * w, 0.19 * h),
          M.HAZARD if kind == "construction_worker" else M.CLOTH, top)
    head = 0.085 * h
    b.add(ELLIPSOID, (0, 0, h - head), (head * 0.9, head * 0.85, head), M.SKIN, _pick(rng, SKIN_COLORS))
    return Shape(category, (w, l, h), b.done())


def barrier(rng) -> Shape:
    w, l, h = rng.uniform(0.4, 0.6), rng.uniform(1.8, 2.6), rng.uniform(0.85, 1.1)
    b = _Builder("movable_object.barrier")
    striped = rng.random() < 0.5
    material, color = (M.STRIPES, (0.85, 0.1, 0.1)) if striped else (M.CONCRETE, (0.7, 0.7, 0.68))
    b.box(-l / 2, l / 2, -w / 2, w / 2, 0.0, 0.3 * h, material, color)
    b.box(-l / 2, l / 2, -w / 4, w / 4, 0.3 * h, h, material, color)
    return Shape("movable_object.barrier", (w, l, h), b.done())


def traffic_cone(rng) -> Shape:
    r, h = rng.uniform(0.17, 0.23), rng.uniform(0.6, 1.0)
    b = _Builder("movable_object.trafficcone")
    b.box(-r, r, -r, r, 0.0, 0.04, M.TYRE, (0.05, 0.05, 0.05))
    b.add(FRUSTUM, (0, 0, (0.04 + h) / 2), (r * 0.85, r * 0.85, (h - 0.04) / 2), M.CONE, (1.0, 0.4, 0.05), taper=0.12)
    return Shape("movable_object.trafficcone", (2 * r, 2 * r, h), b.done())


def trash_bin(rng) -> Shape:
    w, l, h = rng.uniform(0.55, 0.7), rng.uniform(0.6, 0.8), rng.uniform(0.95, 1.15)
    b = _Builder("movable_object.pushable_pullable")
    color = _pick(rng, ((0.1, 0.35, 0.15), (0.2, 0.2, 0.22), (0.1, 0.2, 0.5)))
    b.box(-l / 2, l / 2, -w / 2, w / 2, 0.0, h, M.PLASTIC, color)
    return Shape("movable_object.pushable_pullable", (w, l, h), b.done())


def bicycle_rack(rng) -> Shape:
    w, l, h = 0.5, rng.uniform(2.0, 3.5), 0.8
    b = _Builder("static_object.bicycle_rack")
    b.box(-l / 2, l / 2, -0.04, 0.04, 0.7, 0.8, M.METAL, (0.6, 0.6, 0.62))
    for x in np.linspace(-l / 2 + 0.05, l / 2 - 0.05, 4):
        b.box(x - 0.04, x + 0.04, -w / 2, w / 2, 0.0, 0.7, M.METAL, (0.6, 0.6, 0.62))
    return Shape("static_object.bicycle_rack", (w, l, h), b.done())
