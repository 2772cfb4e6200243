"""Label sets of Occ3D-nuScenes, Occ3D-Waymo and the nuScenes detection task (docs/architecture.md sec. 1)."""

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
NUM_BOX_CLASSES = 10

# Box class -> occupancy class (same names in both label sets).
BOX_TO_OCC = tuple(OCC_CLASSES.index(name) for name in BOX_CLASSES)

WAYMO_OCC_CLASSES = (
    "general_object", "vehicle", "pedestrian", "sign", "cyclist", "traffic_light", "pole",
    "construction_cone", "bicycle", "motorcycle", "building", "vegetation", "tree_trunk",
    "road", "walkable", "free",
)
WAYMO_FREE_LABEL = 15

# RGB colours for pictures (BEV maps, point clouds), index = occupancy label.
OCC_COLORS = (
    (0, 0, 0), (255, 120, 50), (255, 192, 203), (255, 255, 0), (0, 150, 245),
    (0, 255, 255), (200, 180, 0), (255, 0, 0), (255, 240, 150), (135, 60, 0),
    (160, 32, 240), (255, 0, 255), (139, 137, 137), (75, 0, 75), (150, 240, 80),
    (230, 230, 250), (0, 175, 0), (255, 255, 255),
)
