"""OPUS's test-time padding of the grid (odg_ros/network/padding.py) against a float64
reference written with SciPy's grey-scale filters, and hand-made cases: ties between classes,
thresholds on a score step, grids of one voxel along an axis, batches, the full Occ3D size."""
import numpy as np
import pytest
import torch
from scipy import ndimage

from odg_ros.network.padding import OccupancyPadding, pad_occupancy, passing_cutoff

FREE = 17


def passes(score, threshold):
    """score / 255 > threshold as the grid's float32 arithmetic has it."""
    return (np.float32(score) / np.float32(255.0)) > np.float32(threshold)


def reference(labels, confidence, threshold, num_classes=FREE):
    """Per class: top-class score grid, 3x3x3 max then min filter (the border ignored); voxels
    whose own score passes keep theirs, the others take the closed argmax (the first class
    on a tie) if it passes."""
    score = np.where(labels != num_classes, confidence / 255.0, 0.0)
    closed = np.zeros((num_classes,) + labels.shape)
    for c in range(num_classes):
        grid = np.where(labels == c, score, 0.0)
        dilated = ndimage.maximum_filter(grid, size=3, mode="constant", cval=-np.inf)
        closed[c] = ndimage.minimum_filter(dilated, size=3, mode="constant", cval=np.inf)
    top, best = closed.max(axis=0), closed.argmax(axis=0)
    keep = (labels != num_classes) & passes(np.round(score * 255), threshold)
    filled = ~keep & passes(np.round(top * 255), threshold)
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


def random_grid(rng, shape, density, classes=range(FREE)):
    labels = np.where(rng.random(shape) < density, rng.choice(list(classes), shape), FREE)
    confidence = np.where(labels != FREE, rng.integers(1, 256, shape), 0)
    return labels.astype(np.uint8), confidence.astype(np.uint8)


@pytest.mark.parametrize("shape", [(1, 6, 5), (7, 1, 4), (6, 5, 1), (1, 1, 1), (2, 3, 2)])
def test_grids_one_voxel_thin_match_the_reference(shape):
    rng = np.random.default_rng(sum(shape))
    for density in (0.3, 0.9):
        labels, confidence = random_grid(rng, shape, density, classes=(0, 5, 16))
        got = pad(labels, confidence, 0.3)
        want = reference(labels, confidence, 0.3)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_a_tie_between_classes_goes_to_the_first_class():
    """Two classes close a hole with the same score: the lower class index wins (as
    torch.max(dim) and np.argmax pick), whichever of them lies where."""
    for even, odd in ((9, 2), (2, 9)):
        labels = np.full((5, 5, 3), FREE, dtype=np.uint8)
        labels[0::2, :, 1], labels[1::2, :, 1] = even, odd    # rows of alternating classes
        confidence = np.where(labels != FREE, 180, 0).astype(np.uint8)
        labels[2, 2, 1], confidence[2, 2, 1] = FREE, 0        # a hole both surround
        got_labels, got_conf = pad(labels, confidence, 0.3)
        want = reference(labels, confidence, 0.3)
        np.testing.assert_array_equal(got_labels, want[0])
        np.testing.assert_array_equal(got_conf, want[1])
        assert got_labels[2, 2, 1] == 2 and got_conf[2, 2, 1] == 180


@pytest.mark.parametrize("threshold", [76 / 255, 76.5 / 255, 77 / 255, 0.3, 0.0, -0.5, 1.0])
def test_thresholds_on_a_score_step(threshold):
    """The threshold compares scores as the grid's float32 arithmetic does, also right on
    one of the 1/255 steps, below every score and above them all."""
    rng = np.random.default_rng(int(threshold * 1000) % 97)
    labels, confidence = random_grid(rng, (9, 8, 6), 0.5, classes=(1, 4, 7))
    confidence = np.where(labels != FREE, rng.integers(74, 80, labels.shape), 0).astype(np.uint8)
    got = pad(labels, confidence, threshold)
    want = reference(labels, confidence, threshold)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    scores = torch.arange(256, dtype=torch.uint8)
    passing = scores.float() / 255.0 > threshold            # the float32 comparison itself
    assert passing_cutoff(threshold) == (int(passing.nonzero()[0]) if passing.any() else 256)


def test_each_grid_of_a_batch_is_padded_on_its_own():
    rng = np.random.default_rng(5)
    grids = [random_grid(rng, (6, 7, 5), d) for d in (0.2, 0.7, 0.0)]
    labels = torch.from_numpy(np.stack([g[0] for g in grids]))
    confidence = torch.from_numpy(np.stack([g[1] for g in grids]))
    got_labels, got_conf = pad_occupancy(labels, confidence, FREE, 0.4)
    for b, (lab, conf) in enumerate(grids):
        want = reference(lab, conf, 0.4)
        np.testing.assert_array_equal(got_labels[b].numpy(), want[0])
        np.testing.assert_array_equal(got_conf[b].numpy(), want[1])


def test_the_occ3d_grid_matches_the_reference():
    """200 x 200 x 16 with 17 classes, the node's grid: surfaces with holes and noise."""
    rng = np.random.default_rng(200)
    shape = (200, 200, 16)
    labels = np.full(shape, FREE, np.uint8)
    labels[:, :, 3] = rng.choice([11, 12, 13], (200, 200))            # the ground
    noise = rng.random(shape) < 0.05
    labels[noise] = rng.integers(0, FREE, noise.sum())
    labels[rng.random(shape) < 0.1] = FREE                            # holes
    confidence = np.where(labels != FREE, rng.integers(60, 256, shape), 0).astype(np.uint8)
    padding = OccupancyPadding(shape, FREE, 0.3)
    got = [t[0].numpy() for t in padding(torch.from_numpy(labels)[None],
                                           torch.from_numpy(confidence)[None])]
    want = reference(labels, confidence, 0.3)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert (got[0] != labels).sum() > 1000                            # it did fill holes


def test_padding_traces_as_one_graph():
    """No host read and no graph break: the online step compiles it with fullgraph=True."""
    padding = OccupancyPadding((6, 5, 4), FREE, 0.3)
    rng = np.random.default_rng(1)
    labels, confidence = (torch.from_numpy(t)[None] for t in random_grid(rng, (6, 5, 4), 0.4))
    compiled = torch.compile(padding, fullgraph=True, dynamic=False, backend="aot_eager")
    for got, want in zip(compiled(labels, confidence), padding(labels, confidence)):
        assert torch.equal(got, want)


@pytest.mark.parametrize("chunk", [1, 4, FREE])
def test_every_chunk_of_classes_gives_the_same_grid(chunk):
    """Classes filtered one at a time (the CPU), in chunks or all at once (a GPU): the same
    grid as the reference, on random grids and on surfaces with holes of many classes."""
    rng = np.random.default_rng(chunk)
    shape = (23, 19, 7)
    cases = [random_grid(rng, shape, density) for density in (0.05, 0.4, 0.95)]
    labels = np.full(shape, FREE, np.uint8)
    labels[:, :, 2] = rng.choice([11, 12, 13], shape[:2])
    labels[rng.random(shape) < 0.1] = FREE
    cases.append((labels, np.where(labels != FREE, rng.integers(60, 256, shape), 0)
                  .astype(np.uint8)))
    padding = OccupancyPadding(shape, FREE, 0.3)
    padding.chunk = chunk
    for labels, confidence in cases:
        got = [t[0].numpy() for t in padding(torch.from_numpy(labels)[None],
                                               torch.from_numpy(confidence)[None])]
        want = reference(labels, confidence, 0.3)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
