"""Hard cases of the post-processing (network/postprocess.py): means on voxel boundaries, on
the grid's faces and far outside it (1e30 m, inf, NaN), scores exactly at the threshold and
logits of +-inf / NaN, box codes that overflow exp().

Already covered by test_network.py (not repeated): NaN points ignored, confident points
voxelised near their centroid, box decoding of plain codes.
"""
import math

import torch
from hypothesis import given
from hypothesis import strategies as st

from odg_ros.classes import FREE_LABEL
from odg_ros.model_config import load_preset
from odg_ros.network.outputs import LayerOutput, ODGOutput
from odg_ros.network.postprocess import (box_list, decode_box_code, occupancy_grid,
                                       stray_voxels)

from testing.hard_cases import HARD

CFG = load_preset("odg_cpu")


def output(means, logits, boxes=None, box_logits=None):
    layer = LayerOutput(means, logits, torch.ones_like(means), torch.zeros(*means.shape[:-1], 4),
                        torch.ones(means.shape[:-1]), boxes, box_logits)
    return ODGOutput(init_means=means[:, :, :1], layers=[layer], num_dynamic=0)


coordinate = (st.floats(-45.0, 45.0) | st.sampled_from([-40.0, 40.0, -1.0, 5.4, 0.0, 0.4,
                                                         -38.8, 1e30, -1e30, math.inf,
                                                         -math.inf, math.nan]))
logit = st.floats(-30, 30) | st.sampled_from([0.0, math.inf, -math.inf, math.nan])


@HARD
@given(points=st.lists(st.tuples(coordinate, coordinate, coordinate, logit), min_size=1,
                       max_size=12))
def test_grid_from_extreme_means_and_logits(points):
    """Every labelled voxel holds a kept point: finite mean inside the half-open grid,
    within 3 m of its query centroid, best score > 0.5 (NaN scores never pass)."""
    means = torch.tensor([[[list(p[:3]) for p in points]]])             # one query, K points
    logits = torch.full((1, 1, len(points), 17), -30.0)
    for k, p in enumerate(points):
        logits[0, 0, k, 5] = p[3]
    labels, confidence = occupancy_grid(output(means, logits), CFG)
    assert labels.dtype == torch.uint8 and labels.shape == (1, 200, 200, 16)
    occupied = (labels != FREE_LABEL).nonzero()[:, 1:]
    lo = torch.tensor(CFG.pc_range[:3], dtype=torch.float64)
    centroid = means.double().mean(dim=2)[0, 0]
    allowed = set()
    for k, p in enumerate(points):
        m = torch.tensor(p[:3], dtype=torch.float64)
        score = torch.sigmoid(torch.tensor(p[3], dtype=torch.float64))
        if not (torch.isfinite(m).all() and score > CFG.score_threshold):
            continue
        if not (m.float().double() - centroid).norm() <= CFG.max_distance_to_centroid + 1e-4:
            continue
        index = torch.floor((means[0, 0, k] - lo.float()) / CFG.voxel_size).long()
        if ((index >= 0) & (index < torch.tensor(CFG.grid_shape))).all():
            allowed.add(tuple(index.tolist()))
    assert {tuple(v) for v in occupied.tolist()} <= allowed
    assert (labels[labels != FREE_LABEL] == 5).all()
    assert (confidence[labels == FREE_LABEL] == 0).all()


def test_point_on_the_upper_grid_face_is_outside_and_lower_face_inside():
    means = torch.tensor([[[[40.0, 0.0, 0.0], [-40.0, -40.0, -1.0], [0.0, 40.0, 5.4]]]])
    logits = torch.full((1, 1, 3, 17), 10.0)
    labels, _ = occupancy_grid(output(means, logits), CFG.replace(max_distance_to_centroid=1e9))
    occupied = (labels != FREE_LABEL).nonzero()[:, 1:].tolist()
    assert occupied == [[0, 0, 0]]                # [lo, hi): the max faces are outside


def test_box_codes_that_overflow_exp_decode_to_finite_boxes_or_are_dropped():
    codes = torch.tensor([[[0, 0, 0, 1e4, -1e4, 88.8, 0.0, 0.0, 1e38, -1e38],
                           [1, 2, 0, 0.5, 1.5, 0.4, math.nan, 1.0, 0, 0],
                           [1, 2, 0, math.inf, 1.5, 0.4, 0.0, 1.0, 0, 0],
                           [5, 5, 0, 0.5, 1.5, 0.4, 0.0, 0.0, 0, 0]]])
    decoded = decode_box_code(codes)
    assert torch.isfinite(decoded[0, 0, :6]).all() and decoded[0, 0, 3] <= 50.0 + 1e-3
    assert decoded[0, 0, 4] == 0.0                       # exp(-1e4): a zero size, not NaN
    assert decoded[0, 3, 6] == 0.0                       # atan2(0, 0) = 0, a defined yaw
    layer_logits = torch.full((1, 1, 1, 17), -10.0)
    out = output(torch.zeros(1, 1, 1, 3), layer_logits, codes, torch.full((1, 4, 10), 5.0))
    boxes = box_list(out, CFG)[0]
    assert all(all(math.isfinite(v) for v in b["center"] + b["size"] + b["velocity"] + [b["yaw"]])
               for b in boxes)
    assert len(boxes) == 2                               # the NaN yaw and inf size are dropped


def test_stray_voxels_are_the_passing_points_the_grid_drops_for_their_distance():
    """Of one query's points: a stray one (far from the centroid, score passing) marks its
    voxel; the kept ones, a far one whose score fails and one outside the grid do not; the
    grid stays free there. A query with a NaN point has no centroid: nothing strays."""
    far = [30.0, 0.0, 1.0]
    means = torch.tensor([[[[0.0, 0.0, 1.0]] * 36 + [far, [-30.0, 0.0, 1.0], [0.0, -60.0, 1.0],
                                                      [0.0, 0.2, 1.0]]]])
    logits = torch.full((1, 1, 40, 17), 5.0)
    logits[0, 0, 37] = -5.0                                      # the far one that fails
    labels, _ = occupancy_grid(output(means, logits), CFG)
    stray = stray_voxels(means, logits, CFG)
    assert stray.dtype == torch.bool and stray.shape == (1, 200 * 200 * 16)
    index = ((torch.tensor(far) - torch.tensor(CFG.pc_range[:3])) / CFG.voxel_size).floor()
    flat = int((index[0] * 200 + index[1]) * 16 + index[2])
    assert stray[0].nonzero().view(-1).tolist() == [flat]
    assert labels.view(-1)[flat] == FREE_LABEL
    assert (labels != FREE_LABEL).sum() == 1                     # the kept points: one voxel
    means[0, 0, 0, 0] = math.nan
    assert not stray_voxels(means, logits, CFG).any()
