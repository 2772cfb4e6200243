"""Box detection AP: against the nuScenes devkit on random scenes, and hand-checked cases."""
import numpy as np
import pytest

# the reference: nuscenes-devkit is a project dependency (Makefile), so no skip
from nuscenes.eval.common.data_classes import EvalBoxes
from nuscenes.eval.common.utils import center_distance
from nuscenes.eval.detection.algo import accumulate, calc_ap
from nuscenes.eval.detection.data_classes import DetectionBox

from odg_ros.classes import BOX_CLASSES
from odg_ros.metrics.detection import (DetectionScore, average_precision, format_detection,
                                       greedy_match)


def random_split(rng, samples=6, classes=(0, 5, 8)):
    split = []
    for _ in range(samples):
        m = int(rng.integers(0, 9))
        gt = np.zeros((m, 9))
        gt[:, :2] = rng.uniform(-30, 30, (m, 2))
        gt[:, 3:6] = 1.0
        gt_labels = rng.choice(classes, m)
        # detections: jittered copies of some GT (true positives at some thresholds) + clutter
        hit = rng.random(m) < 0.7
        pred = np.concatenate([gt[hit], np.zeros((int(rng.integers(0, 6)), 9))])
        pred[hit.sum():, :2] = rng.uniform(-30, 30, (len(pred) - hit.sum(), 2))
        pred[:, :2] += rng.normal(0, 1.0, (len(pred), 2))
        pred[:, 3:6] = 1.0
        labels = np.concatenate([gt_labels[hit], rng.choice(classes, len(pred) - hit.sum())])
        # scores on a coarse grid, so that ties (the sort order's corner) happen
        scores = np.round(rng.random(len(pred)), 1)
        split.append((pred, labels, scores, gt, gt_labels))
    return split


def devkit_ap(split, label, threshold):
    def boxes(centres, labels, scores, token):
        return [DetectionBox(sample_token=token, translation=(float(c[0]), float(c[1]), 0.0),
                             size=(1.0, 1.0, 1.0), rotation=(1.0, 0.0, 0.0, 0.0),
                             velocity=(0.0, 0.0), detection_name=BOX_CLASSES[int(lab)],
                             detection_score=float(s), attribute_name="")
                for c, lab, s in zip(centres, labels, scores)]

    gt, pred = EvalBoxes(), EvalBoxes()
    for i, (p, pl, ps, g, gl) in enumerate(split):
        gt.add_boxes(f"s{i}", boxes(g, gl, np.full(len(g), -1.0), f"s{i}"))
        pred.add_boxes(f"s{i}", boxes(p, pl, ps, f"s{i}"))
    return calc_ap(accumulate(gt, pred, BOX_CLASSES[label], center_distance, threshold),
                   0.1, 0.1)


@pytest.mark.parametrize("seed", range(4))
def test_ap_matches_nuscenes_devkit(seed):
    split = random_split(np.random.default_rng(seed))
    score = DetectionScore()
    for sample in split:
        score.add(*sample)
    compared = 0
    for label in (0, 5, 8):
        for threshold in (0.5, 1.0, 2.0, 4.0):
            ours = score.class_ap(label, threshold)
            if ours is None:        # no GT of this class: the devkit says 0, we leave it out
                assert not any((s[4] == label).any() for s in split)
                continue
            assert ours == pytest.approx(devkit_ap(split, label, threshold), abs=1e-12)
            compared += 1
    assert compared >= 8


def perfect(samples=3):
    rng = np.random.default_rng(0)
    out = []
    for _ in range(samples):
        gt = np.zeros((4, 9))
        gt[:, :2] = rng.uniform(-30, 30, (4, 2))
        labels = np.array([0, 0, 5, 8])
        out.append((gt.copy(), labels, rng.random(4), gt, labels))
    return out


def test_perfect_detections_score_100_and_absent_classes_are_none():
    score = DetectionScore()
    for sample in perfect():
        score.add(*sample)
    result = score.result()
    assert result["mAP"] == 100.0
    assert result["per_class"]["car"]["AP@0.5"] == 100.0
    assert result["per_class"]["truck"]["AP"] is None           # no truck in the GT
    assert result["gt_boxes"] == result["pred_boxes"] == 12
    assert "mAP 100.00" in format_detection(result)


def test_wrong_class_far_and_missing_detections_score_zero():
    for change in ("class", "far", "none"):
        score = DetectionScore()
        for pred, labels, scores, gt, gt_labels in perfect():
            if change == "class":
                labels = (labels + 1) % len(BOX_CLASSES)
            elif change == "far":
                pred = pred + np.array([4.0] + [0.0] * 8)   # 4 m off: not < 4 m
            else:
                pred, labels, scores = np.zeros((0, 9)), np.zeros(0, int), np.zeros(0)
            score.add(pred, labels, scores, gt, gt_labels)
        assert score.result()["mAP"] == 0.0, change


def test_no_gt_at_all_gives_none():
    score = DetectionScore()
    score.add(np.zeros((2, 9)), [0, 1], [0.9, 0.2], np.zeros((0, 9)), [])
    result = score.result()
    assert result["mAP"] is None and result["AP@2"] is None


def test_greedy_match_takes_each_gt_once_and_threshold_is_strict():
    gt = np.array([[0.0, 0.0], [10.0, 0.0]])
    pred = np.array([[0.1, 0.0], [0.2, 0.0], [11.0, 0.0], [10.0, 0.0]])
    # the second prediction finds GT 0 taken; its nearest free GT (10 m) is too far
    np.testing.assert_array_equal(greedy_match(pred, gt, 2.0), [True, False, True, False])
    np.testing.assert_array_equal(greedy_match(np.array([[1.0, 0.0]]), gt[:1], 1.0), [False])
    assert greedy_match(pred, np.zeros((0, 2)), 2.0).tolist() == [False] * 4


def test_average_precision_hand_values():
    # one GT, found by the only prediction: precision 1 at every recall -> AP 1
    assert average_precision([True], 1) == pytest.approx(1.0)
    # a false positive after it sits at the same recall 1: the interpolation (np.interp, last
    # of equal x) gives the 100 % recall bin its precision 0.5, as the devkit does
    assert average_precision([True, False], 1) == pytest.approx((89 + 0.4 / 0.9) / 90)
    # two GT, one found with precision 1, then nothing: recall stops at 0.5, AP counts
    # the 40 recall bins (0.11 .. 0.50) of 90 at precision (1 - 0.1) / 0.9
    assert average_precision([True], 2) == pytest.approx(40 / 90)
    assert average_precision([], 3) == 0.0
    with pytest.raises(ValueError):
        average_precision([True], 0)


@pytest.mark.parametrize("bad", ["nan_score", "nan_centre", "label", "count"])
def test_bad_input_is_refused(bad):
    pred, labels, scores = np.zeros((2, 9)), np.array([0, 1]), np.array([0.5, 0.4])
    if bad == "nan_score":
        scores[0] = np.nan
    elif bad == "nan_centre":
        pred[1, 0] = np.inf
    elif bad == "label":
        labels[0] = len(BOX_CLASSES)
    else:
        scores = scores[:1]
    with pytest.raises(ValueError):
        DetectionScore().add(pred, labels, scores, np.zeros((0, 9)), [])


def test_best_f1_threshold_hand_values():
    gt = np.array([[0.0, 0.0] + [1.0] * 7, [10.0, 0.0] + [1.0] * 7])
    pred = np.array([[30.0, 0.0], [0.5, 0.0], [10.0, 1.0], [-20.0, 0.0]])
    score = DetectionScore()
    # a far box scored 0.95, the two right ones 0.9 and 0.8, a far one 0.3 (another sample's
    # box ties 0.8 with a wrong class: it must go with the 0.8 cut)
    score.add(pred, [0, 0, 0, 0], [0.95, 0.9, 0.8, 0.3], gt, [0, 0])
    score.add(np.array([[5.0, 5.0]]), [8], [0.8], np.zeros((0, 9)), [])
    found = score.best_f1_threshold(2.0)
    # cuts: 0.95 -> F1 0; 0.9 -> 2/(2+2); 0.8 (two boxes) -> 2*2/(4+2); 0.3 -> 4/(5+2)
    assert found["threshold"] == pytest.approx(0.55)
    assert found["f1"] == pytest.approx(4 / 6)
    assert (found["precision"], found["recall"]) == (pytest.approx(0.5), 1.0)
    # nothing right: publish nothing
    empty = DetectionScore()
    empty.add(pred, [1, 1, 1, 1], [0.9, 0.8, 0.7, 0.6], gt, [0, 0])
    assert empty.best_f1_threshold()["threshold"] == 1.0
