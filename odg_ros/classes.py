"""Label sets of Occ3D-nuScenes, Occ3D-Waymo and the nuScenes detection task (docs/architecture.md sec. 1)."""
from __future__ import annotations

from dataclasses import dataclass

OCC_CLASSES = (
    "others", "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle",
    "pedestrian", "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat",
    "sidewalk", "terrain", "manmade", "vegetation", "free",
)
FREE_LABEL = 17
NUM_OCC_CLASSES = 17  # semantic classes without "free"

# OPUS per-class weights of the point classification (focal) loss, classes 0..16.
OCC_CLASS_WEIGHTS = (10, 5, 10, 5, 5, 10, 10, 5, 10, 5, 5, 1, 5, 1, 1, 2, 1)

# Occupancy classes that move (the paper's "dynamic" categories plus the small movers).
DYNAMIC_OCC_CLASSES = ("bicycle", "bus", "car", "construction_vehicle", "motorcycle",
                       "pedestrian", "trailer", "truck")

BOX_CLASSES = (
    "car", "truck", "construction_vehicle", "bus", "trailer", "barrier", "motorcycle",
    "bicycle", "pedestrian", "traffic_cone",
)
WAYMO_OCC_CLASSES = (
    "general_object", "vehicle", "pedestrian", "sign", "cyclist", "traffic_light", "pole",
    "construction_cone", "bicycle", "motorcycle", "building", "vegetation", "tree_trunk",
    "road", "walkable", "free",
)
WAYMO_FREE_LABEL = 15

# Focal-loss weights of the Waymo classes 0..14, set by analogy with OCC_CLASS_WEIGHTS (small or
# rare things 10, road users 5, buildings 2, large surfaces 1); not tuned on Occ3D-Waymo.
WAYMO_OCC_CLASS_WEIGHTS = (10, 5, 5, 10, 10, 10, 10, 10, 10, 10, 2, 1, 5, 1, 1)
WAYMO_DYNAMIC_OCC_CLASSES = ("vehicle", "pedestrian", "cyclist", "bicycle", "motorcycle")

# RGB colours for pictures (BEV maps, point clouds), index = occupancy label.
OCC_COLORS = (
    (0, 0, 0), (255, 120, 50), (255, 192, 203), (255, 255, 0), (0, 150, 245),
    (0, 255, 255), (200, 180, 0), (255, 0, 0), (255, 240, 150), (135, 60, 0),
    (160, 32, 240), (255, 0, 255), (139, 137, 137), (75, 0, 75), (150, 240, 80),
    (230, 230, 250), (0, 175, 0), (255, 255, 255),
)

# Waymo classes drawn in the colour of the closest nuScenes class (index into OCC_COLORS).
_WAYMO_COLOR_OF = (0, 4, 7, 9, 2, 5, 6, 8, 2, 6, 15, 16, 16, 11, 13, 17)


@dataclass(frozen=True)
class OccLabels:
    """One occupancy label set: names[0..C-1] are the classes, names[C] = "free" (label C)."""
    dataset: str
    names: tuple[str, ...]
    class_weights: tuple[float, ...]     # focal-loss weight per class (no free)
    dynamic: tuple[str, ...]             # classes that move (the dynamic-class mIoU)
    drivable: tuple[str, ...]            # classes a planner may drive on (BEV map)
    colors: tuple[tuple[int, int, int], ...]

    @property
    def num_classes(self) -> int:
        return len(self.names) - 1

    @property
    def free_label(self) -> int:
        return len(self.names) - 1

    def passable(self) -> tuple[int, ...]:
        """Labels that do not block a planner: free and the drivable classes."""
        return (self.free_label, *(self.names.index(n) for n in self.drivable))


LABEL_SETS = {
    "nuscenes": OccLabels("nuscenes", OCC_CLASSES, OCC_CLASS_WEIGHTS, DYNAMIC_OCC_CLASSES,
                          ("driveable_surface",), OCC_COLORS),
    "waymo": OccLabels("waymo", WAYMO_OCC_CLASSES, WAYMO_OCC_CLASS_WEIGHTS,
                       WAYMO_DYNAMIC_OCC_CLASSES, ("road",),
                       tuple(OCC_COLORS[i] for i in _WAYMO_COLOR_OF)),
}


def occ_labels(dataset: str) -> OccLabels:
    if dataset not in LABEL_SETS:
        raise ValueError(f"unknown dataset {dataset!r} (expected one of {sorted(LABEL_SETS)})")
    return LABEL_SETS[dataset]
