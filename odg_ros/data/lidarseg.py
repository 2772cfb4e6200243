"""nuScenes-lidarseg general classes (32, the ``index`` field of category.json) and their
mapping to the Occ3D-nuScenes labels (classes.OCC_CLASSES, 0..16, 17 = free).

The Occ3D mapping follows the nuScenes-lidarseg challenge merge for the 16 named classes.
The remaining *object-like* general classes (animal, strollers, debris, bicycle racks,
emergency vehicles, static.other, ...) become Occ3D ``others`` (0). ``noise`` and
``vehicle.ego`` carry no occupancy and map to IGNORE.
"""
from __future__ import annotations

import numpy as np

from ..classes import OCC_CLASSES

LIDARSEG_CLASSES = (
    "noise", "animal", "human.pedestrian.adult", "human.pedestrian.child",
    "human.pedestrian.construction_worker", "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer", "human.pedestrian.stroller",
    "human.pedestrian.wheelchair", "movable_object.barrier", "movable_object.debris",
    "movable_object.pushable_pullable", "movable_object.trafficcone",
    "static_object.bicycle_rack", "vehicle.bicycle", "vehicle.bus.bendy", "vehicle.bus.rigid",
    "vehicle.car", "vehicle.construction", "vehicle.emergency.ambulance",
    "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer", "vehicle.truck",
    "flat.driveable_surface", "flat.other", "flat.sidewalk", "flat.terrain", "static.manmade",
    "static.other", "static.vegetation", "vehicle.ego",
)
NUM_LIDARSEG_CLASSES = 32
IGNORE = 255

_TO_OCC_NAME = {
    "noise": None, "vehicle.ego": None,
    "human.pedestrian.adult": "pedestrian", "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian",
    "human.pedestrian.police_officer": "pedestrian",
    "movable_object.barrier": "barrier", "movable_object.trafficcone": "traffic_cone",
    "vehicle.bicycle": "bicycle", "vehicle.bus.bendy": "bus", "vehicle.bus.rigid": "bus",
    "vehicle.car": "car", "vehicle.construction": "construction_vehicle",
    "vehicle.motorcycle": "motorcycle", "vehicle.trailer": "trailer", "vehicle.truck": "truck",
    "flat.driveable_surface": "driveable_surface", "flat.other": "other_flat",
    "flat.sidewalk": "sidewalk", "flat.terrain": "terrain", "static.manmade": "manmade",
    "static.vegetation": "vegetation",
}

# uint8 lookup table: lidarseg index -> Occ3D label (IGNORE for noise / ego).
LIDARSEG_TO_OCC = np.array(
    [IGNORE if _TO_OCC_NAME.get(n, "others") is None else OCC_CLASSES.index(_TO_OCC_NAME.get(n, "others"))
     for n in LIDARSEG_CLASSES], dtype=np.uint8)


def lidarseg_to_occ(labels) -> np.ndarray:
    """Map lidarseg general indices (any int array, values 0..31) to Occ3D labels (uint8)."""
    labels = np.asarray(labels)
    if labels.size and (labels.min() < 0 or labels.max() >= NUM_LIDARSEG_CLASSES):
        raise ValueError(f"lidarseg labels outside 0..31: [{labels.min()}, {labels.max()}]")
    return LIDARSEG_TO_OCC[labels.astype(np.int64)]


def lidarseg_index(name: str) -> int:
    """Index of a general class name, e.g. 'vehicle.car' -> 17."""
    return LIDARSEG_CLASSES.index(name)
