"""Every loss term of a fixed batch stays what the earlier implementation computed (values
recorded from it; float32 math, so within 1e-5 relative), with either nearest-neighbour search."""
import pytest
import torch

from odg_ros.losses import ODGCriterion
from testing.losses import CFG, make_batch, make_output

RECORDED = {
    'occ_chamfer_l0': 47.59703063964844,
    'occ_chamfer_l1': 33.438934326171875,
    'occ_focal_l1': 48.82727813720703,
    'box_l1_l1': 4.9788994789123535,
    'box_focal_l1': 7.495743274688721,
    'render_depth_l1': 9.878207206726074,
    'render_sem_l1': 8.766754150390625,
    'occ_chamfer_l2': 20.069669723510742,
    'occ_focal_l2': 45.8775634765625,
    'box_l1_l2': 5.210910320281982,
    'box_focal_l2': 5.309559345245361,
    'render_depth_l2': 9.647784233093262,
    'render_sem_l2': 4.94801139831543,
    'occ_chamfer_l3': 16.63347625732422,
    'occ_focal_l3': 41.38935852050781,
    'box_l1_l3': 4.624633312225342,
    'box_focal_l3': 3.7280118465423584,
    'render_depth_l3': 8.734694480895996,
    'render_sem_l3': 5.6684651374816895,
    'occ_chamfer_l4': 25.010093688964844,
    'occ_focal_l4': 43.468536376953125,
    'box_l1_l4': 4.6612091064453125,
    'box_focal_l4': 6.1862945556640625,
    'render_depth_l4': 9.656582832336426,
    'render_sem_l4': 8.174391746520996,
    'occ_chamfer_l5': 14.401039123535156,
    'occ_focal_l5': 41.4285774230957,
    'box_l1_l5': 5.413488864898682,
    'box_focal_l5': 5.464452743530273,
    'render_depth_l5': 9.36337661743164,
    'render_sem_l5': 4.898521900177002,
    'occ_chamfer_l6': 17.336761474609375,
    'occ_focal_l6': 46.70780563354492,
    'box_l1_l6': 5.05213737487793,
    'box_focal_l6': 9.40009593963623,
    'render_depth_l6': 8.693665504455566,
    'render_sem_l6': 4.160843372344971,
    'loss': 457.87713623046875,
}


@pytest.mark.parametrize("nn_method", ["kdtree", "cdist"])
def test_every_loss_term_of_a_fixed_batch_is_unchanged(nn_method):
    criterion = ODGCriterion(CFG, render_pixels_per_camera=16, seed=3, nn_method=nn_method)
    losses = criterion(make_output(), make_batch())
    assert set(losses) == set(RECORDED)
    for name, value in losses.items():
        assert float(value.detach()) == pytest.approx(RECORDED[name], rel=1e-5), name
