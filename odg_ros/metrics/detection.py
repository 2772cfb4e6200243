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

What the nuScenes benchmark does and this does not: per-class evaluation ranges (here the
caller keeps the boxes inside the occupancy grid), removal of GT boxes without LiDAR/radar
points, and the true-positive error metrics of NDS.
"""
from __future__ import annotations

import math

import numpy as np

from ..classes import BOX_CLASSES

DISTANCE_THRESHOLDS = (0.5, 1.0, 2.0, 4.0)
MIN_RECALL = 0.1
MIN_PRECISION = 0.1
RECALL_POINTS = 101


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


def greedy_match(pred_xy: np.ndarray, gt_xy: np.ndarray, threshold: float) -> np.ndarray:
    """Predictions (already in score order) [N, 2] against GT [M, 2] of one sample and class:
    each prediction takes its nearest untaken GT; -> [N] bool, true positive or not."""
    matched = np.zeros(len(pred_xy), dtype=bool)
    if not len(gt_xy):
        return matched
    distance = np.linalg.norm(pred_xy[:, None, :] - gt_xy[None, :, :], axis=-1)
    taken = np.zeros(len(gt_xy), dtype=bool)
    for i in range(len(pred_xy)):
        row = np.where(taken, np.inf, distance[i])
        j = int(np.argmin(row))
        if row[j] < threshold:
            taken[j] = matched[i] = True
    return matched


def _check(boxes, labels, scores=None, what="boxes"):
    boxes = np.asarray(boxes, dtype=np.float64)
    boxes = boxes.reshape(0, 2) if boxes.size == 0 else boxes
    labels = np.asarray(labels, dtype=np.int64).reshape(-1)
    if boxes.ndim != 2 or boxes.shape[1] < 2 or len(labels) != len(boxes):
        raise ValueError(f"{what}: {boxes.shape} boxes with {labels.shape} labels")
    if not np.isfinite(boxes[:, :2]).all():
        raise ValueError(f"{what}: a box centre is not finite")
    if len(labels) and (labels.min() < 0 or labels.max() >= len(BOX_CLASSES)):
        raise ValueError(f"{what}: labels outside [0, {len(BOX_CLASSES)})")
    if scores is None:
        return boxes, labels
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(scores) != len(boxes) or not np.isfinite(scores).all():
        raise ValueError(f"{what}: scores must be finite, one per box")
    return boxes, labels, scores


class DetectionScore:
    """Accumulates predicted and GT boxes sample by sample; ``result()`` -> mAP and per class."""

    def __init__(self, thresholds=DISTANCE_THRESHOLDS):
        self.thresholds = tuple(float(t) for t in thresholds)
        self.samples: list[tuple] = []

    def add(self, pred_boxes, pred_labels, pred_scores, gt_boxes, gt_labels) -> None:
        """Boxes [N, >=2] (centre x, y first, ego frame, metres), labels index BOX_CLASSES."""
        pred = _check(pred_boxes, pred_labels, pred_scores, "predicted boxes")
        gt = _check(gt_boxes, gt_labels, what="GT boxes")
        self.samples.append((pred, gt))

    def _class_matches(self, label: int, threshold: float):
        """Every prediction of class ``label``: (scores [N], true positive at ``threshold`` m
        [N], position [N]), each sample's predictions in the devkit's order -- score
        descending, ties by the later box first; position: the box's index over all samples
        (samples in order, boxes in order), the devkit's tie-break across samples."""
        scores, matched, position = [np.zeros(0)], [np.zeros(0, bool)], [np.zeros(0, int)]
        offset = 0
        for (boxes, labels, pred_scores), (gt_boxes, gt_labels) in self.samples:
            mine = np.flatnonzero(labels == label)
            order = mine[np.lexsort((-mine, -pred_scores[mine]))]
            scores.append(pred_scores[order])
            position.append(offset + order)
            matched.append(greedy_match(boxes[order][:, :2],
                                        gt_boxes[gt_labels == label][:, :2], threshold))
            offset += len(labels)
        return np.concatenate(scores), np.concatenate(matched), np.concatenate(position)

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
        """{'mAP', 'AP@<t>' (mean over classes), 'per_class': {name: {'AP', 'AP@<t>'...}},
        'gt_boxes', 'pred_boxes', 'samples'} in percent; None where no class has GT."""
        per_class, by_threshold = {}, {t: [] for t in self.thresholds}
        for label, name in enumerate(BOX_CLASSES):
            values = {t: self.class_ap(label, t) for t in self.thresholds}
            if values[self.thresholds[0]] is None:
                per_class[name] = {"AP": None, **{f"AP@{t:g}": None for t in self.thresholds}}
                continue
            for t, v in values.items():
                by_threshold[t].append(v)
            per_class[name] = {"AP": _percent(np.mean(list(values.values()))),
                               **{f"AP@{t:g}": _percent(v) for t, v in values.items()}}
        present = [v["AP"] for v in per_class.values() if v["AP"] is not None]
        return {
            "mAP": round(float(np.mean(present)), 2) if present else None,
            **{f"AP@{t:g}": _percent(np.mean(v)) if v else None for t, v in by_threshold.items()},
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
    for name, values in result["per_class"].items():
        if values["AP"] is not None:
            lines.append(f"  {name:<22} AP {cell(values['AP']):>6}  "
                         + "  ".join(f"{k} {cell(values[k]):>6}" for k in keys))
    return "\n".join(lines)
