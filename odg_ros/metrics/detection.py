"""Box detection score of the dynamic queries: nuScenes-style mean average precision.

The nuScenes detection benchmark's AP (``nuscenes.eval.detection.algo``, test_detection.py
checks ours against it): per class, predictions of all samples sorted by score (descending);
each in turn takes the nearest not-yet-taken GT box of its class in its sample, by the 2-D
centre distance (bird's-eye view), and is a true positive when that distance is below the
threshold. Precision is interpolated on 101 recall points (0 beyond the highest recall
reached), the recall bins up to 10 % and the precision below 10 % are cut off:
    AP = mean(max(precision[recall > 0.1] - 0.1, 0)) / 0.9.
AP is averaged over the thresholds 0.5, 1, 2, 4 m and over the classes that have GT boxes
(classes without GT are reported as None and left out of the mean, as for mIoU).

The true-positive errors of the benchmark (``accumulate`` + ``calc_tp``), for boxes given with
all 9 entries (cx, cy, cz, w, l, h, yaw, vx, vy): at the 2 m threshold each true positive has
    ATE  centre distance in bird's-eye view (m),
    ASE  1 - IoU of the two boxes aligned on a common centre and heading,
    AOE  heading difference (rad; modulo pi for barriers, none for traffic cones),
    AVE  velocity difference in x-y (m/s; none for barriers and traffic cones, and GT boxes
         without a velocity, NaN, leave their pair out);
each error's running mean over the true positives in score order is read off at the scores
where recall crosses 101 interpolation points and averaged over the points from recall > 10 %
to the highest recall reached (1.0, the worst value, when that is not above 10 %). mATE ...
mAVE average the classes that have GT boxes. Beside them, AVE_zero / mAVE_zero: the AVE of the
same matches had every predicted velocity been zero -- the bar a velocity head has to clear
(for parked things zero is right, so a head that has not learned motion scores about this).

What the nuScenes benchmark does and this does not: per-class evaluation ranges (here the
caller keeps the boxes inside the occupancy grid), removal of GT boxes without LiDAR/radar
points, the attribute error (mAAE: boxes here carry no attributes) and so the NDS, which
weighs mAAE in.
"""
from __future__ import annotations

import math

import numpy as np

from ..classes import BOX_CLASSES

DISTANCE_THRESHOLDS = (0.5, 1.0, 2.0, 4.0)
MIN_RECALL = 0.1
MIN_PRECISION = 0.1
RECALL_POINTS = 101
TP_DISTANCE = 2.0
TP_ERRORS = ("ATE", "ASE", "AOE", "AVE")
REPORTED_ERRORS = TP_ERRORS + ("AVE_zero",)
# as the benchmark: a cone has no heading or speed to get right, a barrier no speed
UNDEFINED_ERRORS = {"traffic_cone": ("AOE", "AVE"), "barrier": ("AVE",)}


def average_precision(matched: np.ndarray, num_gt: int, min_recall: float = MIN_RECALL,
                      min_precision: float = MIN_PRECISION) -> float:
    """AP of predictions in score order, ``matched`` [N] bool (true positive or not), against
    ``num_gt`` > 0 GT boxes (nuScenes ``accumulate`` + ``calc_ap``)."""
    matched = np.asarray(matched, dtype=bool)
    if num_gt <= 0:
        raise ValueError("average precision needs at least one GT box")
    if not matched.any():
        return 0.0
    tp = np.cumsum(matched, dtype=np.float64)
    fp = np.cumsum(~matched, dtype=np.float64)
    precision = np.interp(np.linspace(0.0, 1.0, RECALL_POINTS), tp / num_gt, tp / (tp + fp),
                          right=0.0)
    precision = precision[round(100 * min_recall) + 1:] - min_precision
    return float(np.clip(precision, 0.0, None).mean()) / (1.0 - min_precision)


def greedy_assign(pred_xy: np.ndarray, gt_xy: np.ndarray, threshold: float) -> np.ndarray:
    """Predictions (already in score order) [N, 2] against GT [M, 2] of one sample and class:
    each prediction takes its nearest untaken GT; -> [N] index of the GT taken, -1 for none."""
    assigned = np.full(len(pred_xy), -1, dtype=np.int64)
    if not len(gt_xy):
        return assigned
    distance = np.linalg.norm(pred_xy[:, None, :] - gt_xy[None, :, :], axis=-1)
    taken = np.zeros(len(gt_xy), dtype=bool)
    for i in range(len(pred_xy)):
        row = np.where(taken, np.inf, distance[i])
        j = int(np.argmin(row))
        if row[j] < threshold:
            taken[j] = True
            assigned[i] = j
    return assigned


def greedy_match(pred_xy: np.ndarray, gt_xy: np.ndarray, threshold: float) -> np.ndarray:
    """``greedy_assign`` as [N] bool: true positive or not."""
    return greedy_assign(pred_xy, gt_xy, threshold) >= 0


def angle_difference(to_angle: np.ndarray, from_angle: np.ndarray, period: float) -> np.ndarray:
    """Smallest signed angle from ``from_angle`` to ``to_angle`` modulo ``period``, in
    [-pi, pi] (for period 2 pi or pi)."""
    diff = np.mod(to_angle - from_angle + period / 2, period) - period / 2
    return np.where(diff > np.pi, diff - 2 * np.pi, diff)


def true_positive_errors(pred: np.ndarray, gt: np.ndarray, class_name: str) -> np.ndarray:
    """Matched pairs of 9-entry boxes [T, 9] each -> [T, 4] (ATE, ASE, AOE, AVE); NaN where
    the benchmark has no such error (``UNDEFINED_ERRORS``, GT without a velocity)."""
    ate = np.linalg.norm(pred[:, :2] - gt[:, :2], axis=1)
    common = np.prod(np.minimum(pred[:, 3:6], gt[:, 3:6]), axis=1)
    ase = 1.0 - common / (np.prod(pred[:, 3:6], axis=1) + np.prod(gt[:, 3:6], axis=1) - common)
    period = np.pi if class_name == "barrier" else 2 * np.pi
    aoe = np.abs(angle_difference(gt[:, 6], pred[:, 6], period))
    ave = np.linalg.norm(pred[:, 7:9] - gt[:, 7:9], axis=1)
    errors = np.stack([ate, ase, aoe, ave], axis=1)
    for name in UNDEFINED_ERRORS.get(class_name, ()):
        errors[:, TP_ERRORS.index(name)] = np.nan
    return errors


def running_mean(values: np.ndarray) -> np.ndarray:
    """Mean of the non-NaN values up to each position (0 before the first; all ones when every
    value is NaN: the worst error, as the benchmark)."""
    values = np.asarray(values, dtype=np.float64)
    valid = ~np.isnan(values)
    if not valid.any():
        return np.ones(len(values))
    count = np.cumsum(valid)
    total = np.cumsum(np.where(valid, values, 0.0))
    return np.divide(total, count, out=np.zeros_like(total), where=count > 0)


def true_positive_error(matched: np.ndarray, scores: np.ndarray, errors: np.ndarray,
                        num_gt: int, min_recall: float = MIN_RECALL) -> float:
    """One TP error of one class: predictions in score order (``matched`` [N] bool, ``scores``
    [N]), ``errors`` [number of true positives] in the same order -> the mean over the
    recall points above ``min_recall`` up to the highest recall reached; 1.0 without them."""
    matched = np.asarray(matched, dtype=bool)
    if not matched.any():
        return 1.0
    recall = np.cumsum(matched, dtype=np.float64) / num_gt
    confidence = np.interp(np.linspace(0.0, 1.0, RECALL_POINTS), recall, scores, right=0.0)
    # the running mean at each recall point: read at the confidence where that recall is met
    curve = np.interp(confidence[::-1], scores[matched][::-1],
                      running_mean(errors)[::-1])[::-1]
    reached = np.flatnonzero(confidence)
    first, last = round(100 * min_recall) + 1, (int(reached[-1]) if len(reached) else 0)
    return 1.0 if last < first else float(np.mean(curve[first:last + 1]))


def _check(boxes, labels, scores=None, what="boxes"):
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.size == 0:     # keep the columns of a [0, 9] array: an empty sample stays full
        boxes = boxes.reshape(0, boxes.shape[1] if boxes.ndim == 2 and boxes.shape[1] else 2)
    labels = np.asarray(labels, dtype=np.int64).reshape(-1)
    if boxes.ndim != 2 or boxes.shape[1] < 2 or len(labels) != len(boxes):
        raise ValueError(f"{what}: {boxes.shape} boxes with {labels.shape} labels")
    if not np.isfinite(boxes[:, :2]).all():
        raise ValueError(f"{what}: a box centre is not finite")
    if boxes.shape[1] >= 9 and not (np.isfinite(boxes[:, :7]).all() and (boxes[:, 3:6] > 0).all()):
        raise ValueError(f"{what}: a box size or heading is not finite, or a size is <= 0")
    if len(labels) and (labels.min() < 0 or labels.max() >= len(BOX_CLASSES)):
        raise ValueError(f"{what}: labels outside [0, {len(BOX_CLASSES)})")
    if scores is None:
        return boxes, labels
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(scores) != len(boxes) or not np.isfinite(scores).all():
        raise ValueError(f"{what}: scores must be finite, one per box")
    return boxes, labels, scores


class DetectionScore:
    """Accumulates predicted and GT boxes sample by sample; ``result()`` -> mAP and per class,
    and the TP errors when every box has its 9 entries (a centre alone scores only AP)."""

    def __init__(self, thresholds=DISTANCE_THRESHOLDS):
        self.thresholds = tuple(float(t) for t in thresholds)
        self.samples: list[tuple] = []

    def add(self, pred_boxes, pred_labels, pred_scores, gt_boxes, gt_labels) -> None:
        """Boxes [N, >=2] (centre x, y first, ego frame, metres), labels index BOX_CLASSES."""
        pred = _check(pred_boxes, pred_labels, pred_scores, "predicted boxes")
        gt = _check(gt_boxes, gt_labels, what="GT boxes")
        self.samples.append((pred, gt))

    def _class_matches(self, label: int, threshold: float, with_errors: bool = False):
        """Every prediction of class ``label``: (scores [N], true positive at ``threshold`` m
        [N], position [N], and with_errors its ``REPORTED_ERRORS`` [N, 5], NaN rows for
        false positives), each sample's predictions in the devkit's order -- score descending, ties
        by the later box first; position: the box's index over all samples (samples in order,
        boxes in order), the devkit's tie-break across samples."""
        scores, matched, position = [np.zeros(0)], [np.zeros(0, bool)], [np.zeros(0, int)]
        errors = [np.zeros((0, len(REPORTED_ERRORS)))]
        offset = 0
        for (boxes, labels, pred_scores), (gt_boxes, gt_labels) in self.samples:
            mine = np.flatnonzero(labels == label)
            order = mine[np.lexsort((-mine, -pred_scores[mine]))]
            scores.append(pred_scores[order])
            position.append(offset + order)
            gt_mine = gt_boxes[gt_labels == label]
            assigned = greedy_assign(boxes[order][:, :2], gt_mine[:, :2], threshold)
            matched.append(assigned >= 0)
            if with_errors:
                sample_errors = np.full((len(order), len(REPORTED_ERRORS)), np.nan)
                hit = assigned >= 0
                if hit.any():
                    pred, gt = boxes[order][hit], gt_mine[assigned[hit]]
                    still = pred.copy()
                    still[:, 7:9] = 0.0
                    name = BOX_CLASSES[label]
                    sample_errors[hit, :4] = true_positive_errors(pred, gt, name)
                    sample_errors[hit, 4] = true_positive_errors(still, gt, name)[:, 3]
                errors.append(sample_errors)
            offset += len(labels)
        found = np.concatenate(scores), np.concatenate(matched), np.concatenate(position)
        return (*found, np.concatenate(errors)) if with_errors else found

    @property
    def has_full_boxes(self) -> bool:
        """Every box carries all 9 entries (the TP errors need size, yaw, velocity)."""
        return all(len(boxes) == 0 or boxes.shape[1] >= 9
                   for pred, gt in self.samples for boxes in (pred[0], gt[0]))

    def class_tp_errors(self, label: int, threshold: float = TP_DISTANCE) -> dict | None:
        """{'ATE', 'ASE', 'AOE', 'AVE', 'AVE_zero'} of one class (None for the errors the
        class has not); None without GT of that class or without 9-entry boxes."""
        num_gt = sum(int((gt[1] == label).sum()) for _, gt in self.samples)
        if num_gt == 0 or not self.has_full_boxes:
            return None
        scores, matched, position, errors = self._class_matches(label, threshold, True)
        order = np.lexsort((-position, -scores))
        scores, matched, errors = scores[order], matched[order], errors[order][matched[order]]
        undefined = UNDEFINED_ERRORS.get(BOX_CLASSES[label], ())
        return {name: None if name.removesuffix("_zero") in undefined else
                true_positive_error(matched, scores, errors[:, k], num_gt)
                for k, name in enumerate(REPORTED_ERRORS)}

    def class_ap(self, label: int, threshold: float) -> float | None:
        """AP of one class at one distance threshold; None without GT of that class."""
        num_gt = sum(int((gt[1] == label).sum()) for _, gt in self.samples)
        if num_gt == 0:
            return None
        scores, matched, position = self._class_matches(label, threshold)
        return average_precision(matched[np.lexsort((-position, -scores))], num_gt)

    def best_f1_threshold(self, distance: float = 2.0) -> dict:
        """The box score threshold that maximises F1 (all classes pooled, true positive = right
        class within ``distance`` m): {'threshold', 'precision', 'recall', 'f1'} (fractions).
        Without a single true positive: threshold 1.0 -- publish nothing rather than noise.
        A greedy match in score order does not depend on the lower-scored boxes, so each
        prefix of the order is exactly what a threshold keeps."""
        num_gt = sum(len(gt[1]) for _, gt in self.samples)
        per_class = [self._class_matches(label, distance) for label in range(len(BOX_CLASSES))]
        scores = np.concatenate([c[0] for c in per_class])
        matched = np.concatenate([c[1] for c in per_class])
        if not matched.any():
            return {"threshold": 1.0, "precision": None, "recall": 0.0, "f1": 0.0}
        order = np.argsort(-scores, kind="stable")
        scores, matched = scores[order], matched[order]
        tp = np.cumsum(matched)
        f1 = 2 * tp / (np.arange(1, len(scores) + 1) + num_gt)
        # a cut is only possible where the next score is lower (equal scores go together)
        f1 = np.where(np.append(scores[1:] < scores[:-1], True), f1, -1.0)
        best = int(np.argmax(f1))       # the first maximum: the higher threshold on ties
        below = scores[best + 1] if best + 1 < len(scores) else 0.0
        return {"threshold": float(scores[best] + below) / 2,
                "precision": float(tp[best] / (best + 1)), "recall": float(tp[best] / num_gt),
                "f1": float(f1[best])}

    def result(self) -> dict:
        """{'mAP', 'AP@<t>' (mean over classes), 'mATE' .. 'mAVE', 'mAVE_zero', 'per_class':
        {name: {'AP', 'AP@<t>', 'ATE' .. 'AVE', 'AVE_zero'}}, 'gt_boxes', 'pred_boxes',
        'samples'}; AP in percent, the errors in metres, 1 - IoU, radians, m/s (4 decimals);
        None where no class has GT (or the boxes have no 9 entries, for the errors)."""
        per_class, by_threshold = {}, {t: [] for t in self.thresholds}
        by_error = {name: [] for name in REPORTED_ERRORS}
        for label, name in enumerate(BOX_CLASSES):
            values = {t: self.class_ap(label, t) for t in self.thresholds}
            errors = self.class_tp_errors(label) or dict.fromkeys(REPORTED_ERRORS)
            for error, v in errors.items():
                if v is not None:
                    by_error[error].append(v)
            errors = {error: None if v is None else round(v, 4) for error, v in errors.items()}
            if values[self.thresholds[0]] is None:
                per_class[name] = {"AP": None, **{f"AP@{t:g}": None for t in self.thresholds},
                                   **errors}
                continue
            for t, v in values.items():
                by_threshold[t].append(v)
            per_class[name] = {"AP": _percent(np.mean(list(values.values()))),
                               **{f"AP@{t:g}": _percent(v) for t, v in values.items()}, **errors}
        present = [v["AP"] for v in per_class.values() if v["AP"] is not None]
        return {
            "mAP": round(float(np.mean(present)), 2) if present else None,
            **{f"AP@{t:g}": _percent(np.mean(v)) if v else None for t, v in by_threshold.items()},
            **{f"m{e}": round(float(np.mean(v)), 4) if v else None for e, v in by_error.items()},
            "per_class": per_class,
            "gt_boxes": sum(len(gt[1]) for _, gt in self.samples),
            "pred_boxes": sum(len(pred[1]) for pred, _ in self.samples),
            "samples": len(self.samples),
        }


def _percent(value) -> float | None:
    return None if value is None or math.isnan(value) else round(100.0 * float(value), 2)


def format_detection(result: dict) -> str:
    """Short report: mAP, AP per threshold, the classes with GT."""
    cell = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    keys = [k for k in result if k.startswith("AP@")]
    lines = [f"boxes: mAP {cell(result['mAP'])}  ("
             + ", ".join(f"{k} {cell(result[k])}" for k in keys)
             + f"; {result['pred_boxes']} predicted, {result['gt_boxes']} GT, "
               f"{result['samples']} samples)"]
    has_errors = result.get("mATE") is not None
    if has_errors:
        lines.append(f"  TP errors at {TP_DISTANCE:g} m: mATE {result['mATE']:.3f} m, "
                     f"mASE {result['mASE']:.3f}, mAOE {result['mAOE']:.3f} rad, "
                     + ("mAVE -" if result["mAVE"] is None else
                        f"mAVE {result['mAVE']:.3f} m/s (zero velocities: "
                        f"{result['mAVE_zero']:.3f})"))
    error = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    for name, values in result["per_class"].items():
        if values["AP"] is not None:
            lines.append(f"  {name:<22} AP {cell(values['AP']):>6}  "
                         + "  ".join(f"{k} {cell(values[k]):>6}" for k in keys)
                         + ("  " + "  ".join(f"{e} {error(values[e]):>5}" for e in TP_ERRORS)
                            if has_errors else ""))
    return "\n".join(lines)
