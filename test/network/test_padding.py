"""OPUS's test-time padding of the grid (odg_ros/network/padding.py) against a float64
reference written with SciPy's grey-scale filters, and hand-made cases."""
import numpy as np
import pytest
import torch
from scipy import ndimage

from odg_ros.network.padding import pad_occupancy

FREE = 17


def reference(labels, confidence, threshold, num_classes=FREE):
    """Per class: top-class score grid, 3x3x3 max then min filter (the border ignored); voxels
    whose own score passes keep theirs, the others take the closed argmax if it passes."""
    score = np.where(labels != num_classes, confidence / 255.0, 0.0)
    closed = np.zeros((num_classes,) + labels.shape)
    for c in range(num_classes):
        grid = np.where(labels == c, score, 0.0)
        dilated = ndimage.maximum_filter(grid, size=3, mode="constant", cval=-np.inf)
        closed[c] = ndimage.minimum_filter(dilated, size=3, mode="constant", cval=np.inf)
    top, best = closed.max(axis=0), closed.argmax(axis=0)
    keep = (labels != num_classes) & (score > threshold)
    filled = ~keep & (top > threshold)
    out_labels = np.where(keep, labels, np.where(filled, best, num_classes))
    out_conf = np.where(keep, confidence, np.where(filled, np.round(top * 255), 0))
    return out_labels.astype(np.uint8), out_conf.astype(np.uint8)


def pad(labels, confidence, threshold=0.5):
    out = pad_occupancy(torch.from_numpy(labels)[None], torch.from_numpy(confidence)[None],
                        FREE, threshold)
    return out[0][0].numpy(), out[1][0].numpy()


@pytest.mark.parametrize("density", [0.05, 0.3, 0.8])
def test_random_grids_match_the_reference(density):
    rng = np.random.default_rng(int(density * 100))
    shape = (9, 8, 5)
    labels = np.where(rng.random(shape) < density, rng.integers(0, 4, shape) * 4, FREE)
    labels = labels.astype(np.uint8)
    confidence = np.where(labels != FREE, rng.integers(90, 256, shape), 0).astype(np.uint8)
    got = pad(labels, confidence)
    want = reference(labels, confidence, 0.5)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert (got[0] != labels).any()                    # the case does fill or drop voxels


def test_a_hole_is_filled_and_lone_voxels_do_not_grow():
    labels = np.full((10, 10, 6), FREE, dtype=np.uint8)
    confidence = np.zeros_like(labels)
    labels[2:5, 2:5, 2] = 4                            # a 3x3 car plate with a hole
    labels[3, 3, 2] = FREE
    confidence[labels == 4] = 200
    labels[6, 7, 3], confidence[6, 7, 3] = 10, 230     # a lone truck voxel: kept as it is
    labels[0, 8, 0], confidence[0, 8, 0] = 3, 100      # a weak lone bus voxel (0.39): dropped
    labels[8, 1, 4], confidence[8, 1, 4] = 16, 180     # a lone voxel next to a grid corner
    got_labels, got_conf = pad(labels, confidence)
    assert got_labels[3, 3, 2] == 4 and got_conf[3, 3, 2] == 200
    assert got_labels[6, 7, 3] == 10 and (got_labels == 10).sum() == 1
    # the border is ignored by both filters (OPUS pools with implicit -inf padding), so a
    # voxel diagonally next to a corner fills the 2 x 2 x 2 block up to the corner
    assert (got_labels[8:, :2, 4:] == 16).all() and (got_labels == 16).sum() == 8
    assert got_labels[0, 8, 0] == FREE and got_conf[0, 8, 0] == 0
    assert ((got_labels == 4) == np.pad(np.ones((3, 3, 1), bool), ((2, 5), (2, 5), (2, 3)))).all()


def test_free_grid_stays_free():
    labels = np.full((5, 5, 3), FREE, dtype=np.uint8)
    got_labels, got_conf = pad(labels, np.zeros_like(labels))
    assert (got_labels == FREE).all() and (got_conf == 0).all()
