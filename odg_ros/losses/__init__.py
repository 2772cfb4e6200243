"""Training losses of ODG (paper Sec. 3.5, docs/architecture.md sec. 5): one file per loss."""
from .box import BOX_CODE_WEIGHTS, box_loss, decode_boxes, encode_boxes
from .chamfer import (NearestNeighbourIndex, OccupancyTarget, nearest_neighbours,
                      occupancy_loss, occupancy_target)
from .criterion import LAMBDA_3D, ODGCriterion
from .focal import sigmoid_focal_loss
from .matcher import box_match_cost, hungarian_match
from .render_loss import render_layer_weights, render_loss, sample_render_targets

__all__ = [
    "BOX_CODE_WEIGHTS", "box_loss", "decode_boxes", "encode_boxes",
    "NearestNeighbourIndex", "OccupancyTarget", "nearest_neighbours", "occupancy_loss",
    "occupancy_target", "LAMBDA_3D", "ODGCriterion", "sigmoid_focal_loss", "box_match_cost",
    "hungarian_match", "render_layer_weights", "render_loss", "sample_render_targets",
]
