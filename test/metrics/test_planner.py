"""What a planner reads, scored (metrics/planner.py): visibility against mask_camera for voxels
and BEV cells, calibration error, label flips between consecutive outputs; each on cases
whose answer is known by hand."""
import numpy as np
import pytest

from odg_ros.classes import occ_labels
from odg_ros.metrics.planner import (ConfidenceScore, FlipScore, Reliability, VisibilityScore,
                                     bev_cells, carried_indices)
from odg_ros.bev import bev_fields

LABELS = occ_labels("nuscenes")
FREE = LABELS.free_label
SHAPE = (20, 20, 16)
PC_RANGE = (-4.0, -4.0, -1.0, 4.0, 4.0, 5.4)
BAND = (-1.0, 2.0)


def road_grid():
    grid = np.full(SHAPE, FREE, np.uint8)
    grid[:, :, 2] = 11                                          # driveable surface
    return grid


def test_visibility_counts_what_is_published_against_the_truth():
    truth, mask = road_grid(), np.zeros(SHAPE, bool)
    mask[:10] = True                                            # the cameras see x < 10
    grid = truth.copy()
    grid[4, 4, 2] = FREE                                        # a missed road voxel
    observed = np.zeros(SHAPE, bool)
    observed[:15] = True                                        # says it sees x < 15
    score = VisibilityScore()
    args = (PC_RANGE, 0.4, BAND, LABELS)
    score.add(grid, observed, truth, mask, FREE, bev_cells(grid, observed, *args),
              bev_cells(truth, mask, *args))
    voxels = score.result()["voxels"]
    assert voxels["observed_precision"] == pytest.approx(10 / 15, abs=1e-4)
    assert voxels["observed_recall"] == 1.0
    # free and seen: 15 x 20 x 15 voxels said, plus the missed road voxel; right where
    # x < 10 and free in truth (not the missed road voxel)
    said = 15 * 20 * 15 + 1
    assert voxels["free_observed_precision"] == pytest.approx(10 * 20 * 15 / said, abs=1e-4)
    bev = score.result()["bev"]
    # BEV: every column is road (free, 0) where seen from its road up: x < 15 said, x < 10 true
    assert bev["known_precision"] == pytest.approx(10 / 15, abs=1e-4)
    assert bev["free_precision"] == pytest.approx(10 / 15, abs=1e-4)
    assert bev["free_recall"] == 1.0


def test_the_truth_bev_is_the_nodes_bev_of_the_truth_with_mask_camera():
    truth, mask = road_grid(), np.random.default_rng(0).random(SHAPE) > 0.3
    truth[5, 5, 3:6] = 4                                         # a car
    cells = bev_cells(truth, mask, PC_RANGE, 0.4, BAND, LABELS)
    node = bev_fields(truth, PC_RANGE, 0.4, *BAND, LABELS, mask)
    np.testing.assert_array_equal(cells.ravel(), np.frombuffer(node["data"], np.int8))
    assert cells[5, 5] == 100 and (cells == -1).any() and (cells == 0).any()


def test_expected_calibration_error():
    rng = np.random.default_rng(0)
    confidence = rng.random(200_000)
    calibrated = Reliability()
    calibrated.add(confidence, rng.random(200_000) < confidence)
    assert calibrated.result()["ece"] < 0.01
    overconfident = Reliability()      # right 20 points less often than it says
    overconfident.add(confidence, rng.random(200_000) < confidence - 0.2)
    assert overconfident.result()["ece"] == pytest.approx(0.2 - 0.02, abs=0.02)  # (0 floor)
    # weighted by the voxels in each bin: a bin of one wrong voxel barely counts
    weighted = Reliability()
    weighted.add(np.r_[np.full(999, 0.95), 0.05], np.r_[np.ones(950, bool), np.zeros(49, bool),
                                                         True])
    assert weighted.result()["ece"] == pytest.approx(0.95 / 1000, abs=1e-3)
    as_bytes = Reliability()
    as_bytes.add_bytes(np.round(confidence * 255).astype(np.uint8), confidence > 0.5)
    as_floats = Reliability()
    as_floats.add(np.round(confidence * 255) / 255, confidence > 0.5)
    assert as_bytes.result() == as_floats.result()


def test_confidence_right_means_the_class_for_occupied_and_free_for_free():
    truth, mask = road_grid(), np.ones(SHAPE, bool)
    grid = truth.copy()
    grid[:, :, 2][:, :10] = 13                                  # half the road called sidewalk
    confidence = np.where(grid != FREE, 128, 250).astype(np.uint8)
    score = ConfidenceScore(LABELS.names[:-1])
    score.add(grid, confidence, truth, mask, FREE)
    result = score.result()
    assert result["occupied"]["accuracy"] == 0.5
    assert result["occupied"]["ece"] == pytest.approx(abs(128 / 255 - 0.5), abs=1e-4)
    assert result["free"]["accuracy"] == 1.0
    assert set(result["per_class"]) == {"driveable_surface", "sidewalk"}


def test_a_box_is_right_when_a_truth_box_of_its_class_is_within_two_metres():
    score = ConfidenceScore(LABELS.names[:-1])
    boxes = [{"label": 0, "score": 0.9, "center": [0.5, 0.0, 0.0]},     # car near a car
             {"label": 0, "score": 0.8, "center": [0.0, 0.5, 0.0]},     # the same car again
             {"label": 1, "score": 0.7, "center": [10.0, 0.0, 0.0]}]    # truck at a car
    gt = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    score.add_boxes(boxes, gt, np.array([0, 0]))
    scores, right = score.box_pairs()
    np.testing.assert_array_equal(right, [True, False, False])


def test_carried_indices_follow_the_ego_motion():
    before, after = np.eye(4), np.eye(4)
    after[0, 3] = 0.8                                   # the ego moved 2 voxels forward
    index, inside = carried_indices(before, after, SHAPE, PC_RANGE, 0.4)
    X, Y, Z = SHAPE
    i = np.arange(X * Y * Z).reshape(SHAPE)
    assert inside.reshape(SHAPE)[:X - 2].all() and not inside.reshape(SHAPE)[X - 2:].any()
    np.testing.assert_array_equal(index.reshape(SHAPE)[:X - 2], i[2:])


def test_flips_count_static_voxels_only():
    truth = road_grid()
    truth[3, 3, 3:6] = 15                                       # a pole
    truth[8, 8, 3:6] = 4                                        # a car (moves)
    mask = np.ones(SHAPE, bool)
    pose = np.eye(4)
    before = {"grid": truth.copy(), "truth": truth, "mask": mask, "pose": pose}
    flips = FlipScore(LABELS)
    flips.add(before, dict(before), SHAPE, PC_RANGE, 0.4)
    assert flips.result()["flip_rate"] == 0.0
    grid = truth.copy()
    grid[3, 3, 4] = FREE                                        # the pole loses a voxel
    grid[8, 8, 4] = FREE                                        # so does the car
    flips.add(before, {**before, "grid": grid}, SHAPE, PC_RANGE, 0.4)
    result = flips.result()
    static = SHAPE[0] * SHAPE[1] * SHAPE[2] - 3                 # the car's voxels are not
    assert result["flip_rate"] == pytest.approx(1 / (2 * static), abs=1e-7)
    assert result["flip_rate_occupied"] == pytest.approx(1 / (2 * (400 + 3)), abs=1e-7)
    assert result["pairs"] == 2
