"""Box detection AP: against the nuScenes devkit on random scenes, and hand-checked cases."""
import numpy as np
import pytest

# the reference: nuscenes-devkit is a project dependency (Makefile), so no skip
from nuscenes.eval.common.data_classes import EvalBoxes
from nuscenes.eval.common.utils import center_distance
from nuscenes.eval.detection.algo import accumulate, calc_ap, calc_tp
from nuscenes.eval.detection.data_classes import DetectionBox
from pyquaternion import Quaternion

from odg_ros.classes import BOX_CLASSES
from odg_ros.metrics.detection import (REPORTED_ERRORS, TP_ERRORS, DetectionScore,
                                       angle_difference, average_precision, format_detection,
                                       greedy_match, running_mean, true_positive_error,
                                       true_positive_errors)

DEVKIT_TP_METRIC = {"ATE": "trans_err", "ASE": "scale_err", "AOE": "orient_err", "AVE": "vel_err"}


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


def devkit_metric_data(split, label, threshold=2.0):
    """The devkit's ``accumulate`` over a split of (pred, labels, scores, gt, gt_labels) with
    9-entry boxes."""
    def boxes(b, labels, scores, token):
        return [DetectionBox(sample_token=token, translation=tuple(map(float, x[:3])),
                             size=tuple(map(float, x[3:6])),
                             rotation=tuple(Quaternion(axis=(0, 0, 1), angle=float(x[6]))),
                             velocity=tuple(map(float, x[7:9])),
                             detection_name=BOX_CLASSES[int(lab)], detection_score=float(s),
                             attribute_name="")
                for x, lab, s in zip(b, labels, scores)]

    gt, pred = EvalBoxes(), EvalBoxes()
    for i, (p, pl, ps, g, gl) in enumerate(split):
        gt.add_boxes(f"s{i}", boxes(g, gl, np.full(len(g), -1.0), f"s{i}"))
        pred.add_boxes(f"s{i}", boxes(p, pl, ps, f"s{i}"))
    return accumulate(gt, pred, BOX_CLASSES[label], center_distance, threshold)


def devkit_ap(split, label, threshold):
    return calc_ap(devkit_metric_data(split, label, threshold), 0.1, 0.1)


def scored(split) -> DetectionScore:
    """A DetectionScore of every (pred, labels, scores, gt, gt_labels) sample of ``split``."""
    score = DetectionScore()
    for sample in split:
        score.add(*sample)
    return score


def scored_split(make, seed):
    """(the split ``make`` draws from ``seed``, its DetectionScore)."""
    split = make(np.random.default_rng(seed))
    return split, scored(split)


@pytest.mark.parametrize("seed", range(4))
def test_ap_matches_nuscenes_devkit(seed):
    split, score = scored_split(random_split, seed)
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
        gt[:, 3:6] = 1.0
        labels = np.array([0, 0, 5, 8])
        out.append((gt.copy(), labels, rng.random(4), gt, labels))
    return out


def test_perfect_detections_score_100_and_absent_classes_are_none():
    score = scored(perfect())
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
    score.add(np.ones((2, 9)), [0, 1], [0.9, 0.2], np.zeros((0, 9)), [])
    result = score.result()
    assert result["mAP"] is None and result["AP@2"] is None and result["mAVE"] is None


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


@pytest.mark.parametrize("bad", ["nan_score", "nan_centre", "label", "count", "zero_size",
                                 "nan_yaw"])
def test_bad_input_is_refused(bad):
    pred, labels, scores = np.ones((2, 9)), np.array([0, 1]), np.array([0.5, 0.4])
    DetectionScore().add(pred, labels, scores, np.zeros((0, 9)), [])     # valid as it is
    if bad == "nan_score":
        scores[0] = np.nan
    elif bad == "nan_centre":
        pred[1, 0] = np.inf
    elif bad == "label":
        labels[0] = len(BOX_CLASSES)
    elif bad == "zero_size":
        pred[0, 4] = 0.0
    elif bad == "nan_yaw":
        pred[1, 6] = np.nan
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


# ---- the true-positive errors (mATE, mASE, mAOE, mAVE) ----

def random_full_split(rng, samples=8, classes=(0, 5, 8, 9)):
    """Boxes with sizes, headings and velocities (some GT velocities unknown, NaN), classes
    with each special case of the benchmark: car, barrier (heading mod pi, no speed),
    pedestrian, traffic cone (no heading, no speed)."""
    split = []
    for _ in range(samples):
        m = int(rng.integers(0, 9))
        gt = np.concatenate([rng.uniform(-30, 30, (m, 2)), rng.uniform(-1, 1, (m, 1)),
                             rng.uniform(0.3, 5.0, (m, 3)), rng.uniform(-np.pi, np.pi, (m, 1)),
                             rng.normal(0, 4, (m, 2))], axis=1)
        gt[rng.random(m) < 0.2, 7:9] = np.nan
        gt_labels = rng.choice(classes, m)
        hit = rng.random(m) < 0.7
        clutter = int(rng.integers(0, 6))
        pred = np.concatenate([gt[hit], np.zeros((clutter, 9))])
        pred[hit.sum():, :2] = rng.uniform(-30, 30, (clutter, 2))
        pred[:, :2] += rng.normal(0, 1.0, (len(pred), 2))
        pred[:, 3:6] = np.where(np.arange(len(pred))[:, None] < hit.sum(),
                                pred[:, 3:6] * rng.uniform(0.7, 1.4, (len(pred), 3)),
                                rng.uniform(0.3, 5.0, (len(pred), 3)))
        pred[:, 6] = pred[:, 6] + rng.normal(0, 1.5, len(pred))      # any angle, not wrapped
        pred[:, 7:9] = np.nan_to_num(pred[:, 7:9]) + rng.normal(0, 2, (len(pred), 2))
        labels = np.concatenate([gt_labels[hit], rng.choice(classes, clutter)])
        scores = np.round(rng.random(len(pred)), 1)
        split.append((pred, labels, scores, gt, gt_labels))
    return split


@pytest.mark.parametrize("seed", range(4))
def test_tp_errors_match_nuscenes_devkit(seed):
    split, score = scored_split(random_full_split, seed)
    compared = 0
    for label in (0, 5, 8, 9):
        ours = score.class_tp_errors(label)
        if ours is None:
            continue
        data = devkit_metric_data(split, label)
        for name in TP_ERRORS:
            # what the devkit's DetectionEval leaves out (NaN) for cones and barriers
            undefined = (BOX_CLASSES[label] == "traffic_cone" and name in ("AOE", "AVE")
                         or BOX_CLASSES[label] == "barrier" and name == "AVE")
            if undefined:
                assert ours[name] is None
                continue
            assert ours[name] == pytest.approx(calc_tp(data, 0.1, DEVKIT_TP_METRIC[name]),
                                               abs=1e-12), (label, name)
            compared += 1
        # the zero-velocity bar: the devkit's AVE of the same predictions standing still
        if BOX_CLASSES[label] in ("car", "pedestrian"):
            still = [(p * np.r_[np.ones(7), 0.0, 0.0], *rest) for p, *rest in split]
            assert ours["AVE_zero"] == pytest.approx(
                calc_tp(devkit_metric_data(still, label), 0.1, "vel_err"), abs=1e-12)
        else:
            assert ours["AVE_zero"] is None
    assert compared >= 8


def test_tp_error_hand_values():
    gt = np.array([[0, 0, 0, 2, 4, 1, 0.0, 3, 0], [20, 0, 0, 1, 1, 1, 0.0, 0, 0]], float)
    pred = gt.copy()
    pred[0, :2] += (0.6, 0.8)        # 1 m off
    pred[0, 3] = 1.0                 # half as wide: IoU 0.5
    pred[0, 6] = 2 * np.pi - 0.25    # a whole turn and -0.25 rad
    pred[0, 7:9] = (0.0, 4.0)        # (3, 0) -> (0, 4): 5 m/s
    errors = true_positive_errors(pred[:1], gt[:1], "car")
    np.testing.assert_allclose(errors, [[1.0, 0.5, 0.25, 5.0]], atol=1e-12)
    # a barrier turned around is the same barrier, and its speed is not scored
    turned = gt[:1].copy()
    turned[0, 6] = np.pi + 0.1
    barrier = true_positive_errors(turned, gt[:1], "barrier")
    assert barrier[0, 2] == pytest.approx(0.1) and np.isnan(barrier[0, 3])
    assert true_positive_errors(turned, gt[:1], "car")[0, 2] == pytest.approx(np.pi - 0.1)
    # the one box found at every recall point: the error is that box's
    score = DetectionScore()
    score.add(pred[:1], [0], [0.9], gt[:1], [0])
    result = score.result()
    assert (result["mATE"], result["mASE"], result["mAOE"], result["mAVE"]) == \
        pytest.approx((1.0, 0.5, 0.25, 5.0))
    assert result["per_class"]["car"]["AVE"] == pytest.approx(5.0)
    assert result["mAVE_zero"] == pytest.approx(3.0)      # |(3, 0)|: the GT's own speed
    assert "mAVE 5.000 m/s (zero velocities: 3.000)" in format_detection(result)


def test_tp_errors_take_the_worst_value_below_ten_percent_recall():
    # 1 GT of 20 found: recall 5 % never passes 10 % -> 1.0 for every error, as the devkit
    gt = np.zeros((20, 9))
    gt[:, 0] = np.arange(20) * 10.0
    gt[:, 3:6] = 1.0
    score = DetectionScore()
    score.add(gt[:1], [0], [0.5], gt, np.zeros(20, int))
    assert score.class_tp_errors(0) == dict.fromkeys(REPORTED_ERRORS, 1.0)
    assert true_positive_error(np.zeros(3, bool), np.ones(3), np.zeros(0), 5) == 1.0


def test_tp_errors_need_full_boxes_and_unknown_velocities_are_left_out():
    centres = np.zeros((1, 2))
    score = DetectionScore()
    score.add(centres, [0], [0.9], centres, [0])
    assert score.result()["mAP"] == 100.0 and score.result()["mATE"] is None
    assert "TP errors" not in format_detection(score.result())
    # two cars found; the GT velocity of one is unknown: mAVE is the other's error only
    gt = np.array([[0, 0, 0, 1, 1, 1, 0, 1, 0], [9, 0, 0, 1, 1, 1, 0, np.nan, np.nan]])
    pred = gt.copy()
    pred[:, 7:9] = 0.0
    score = DetectionScore()
    score.add(pred, [0, 0], [0.9, 0.8], gt, [0, 0])
    assert score.result()["mAVE"] == pytest.approx(1.0)     # |(0, 0) - (1, 0)|
    # every velocity unknown: the worst value, 1 (as the devkit's cummean)
    np.testing.assert_array_equal(running_mean([np.nan, np.nan]), [1.0, 1.0])
    np.testing.assert_allclose(running_mean([np.nan, 2.0, np.nan, 4.0]), [0.0, 2.0, 2.0, 3.0])


def test_angle_difference_wraps_both_periods():
    assert angle_difference(np.array(0.1), np.array(2 * np.pi - 0.1), 2 * np.pi) == \
        pytest.approx(0.2)
    assert angle_difference(np.array(np.pi), np.array(0.0), np.pi) == pytest.approx(0.0)
    extreme = angle_difference(np.array([1e6, -1e6]), np.array([0.0, 0.0]), 2 * np.pi)
    assert np.all(np.abs(extreme) <= np.pi)
