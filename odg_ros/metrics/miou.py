"""Voxel mIoU of Occ3D occupancy, in the SparseOcc / OPUS or the Occ3D convention.

One (C+1) x (C+1) confusion matrix (rows = GT label, columns = predicted label; C semantic
classes 0..C-1 and ``free`` = C) is summed over every voxel with mask_camera = 1 of every sample
of the split. From the split total:

    IoU_c = conf[c, c] / (sum_j conf[c, j] + sum_i conf[i, c] - conf[c, c])

Two conventions differ only for a class that never occurs in the masked GT of the split:

* ``sparseocc`` (the default; SparseOcc's and OPUS's evaluation): its IoU is NaN even when it
  was predicted, so it is left out of the mean;
* ``occ3d`` (Occ3D's ``Metric_mIoU``): its IoU is 0 when it was predicted (0 / predicted
  voxels), NaN only when it was neither in the GT nor predicted.

On a large split every class occurs and the two agree; on a few keyframes they can differ by
points. mIoU = nanmean of IoU_0..IoU_{C-1} (free excluded). Geometry IoU is the same formula for
"occupied" (any class < C) against free, NaN when the masked GT has no occupied voxel.

Occ3D-nuScenes: C = 17, free = 17. Occ3D-Waymo: C = 15, free = 15.
"""
from __future__ import annotations

import numpy as np

from ..classes import NUM_OCC_CLASSES


def check_labels(name: str, labels: np.ndarray, free_label: int) -> np.ndarray:
    """Integer labels in 0..free_label, or a ValueError that says what is wrong."""
    labels = np.asarray(labels)
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{name}: labels must be integers, got dtype {labels.dtype}")
    if labels.size and (labels.min() < 0 or labels.max() > free_label):
        bad = np.unique(labels[(labels < 0) | (labels > free_label)])[:10].tolist()
        raise ValueError(f"{name}: labels {bad} outside 0..{free_label} "
                         f"({free_label} = free)")
    return labels


MIOU_CONVENTIONS = ("sparseocc", "occ3d")


def iou_from_confusion(confusion: np.ndarray, convention: str = "sparseocc") -> np.ndarray:
    """Per-label IoU [L] from an L x L confusion (rows GT); NaN where the GT row is empty
    (``sparseocc``) or where the label is in neither GT nor prediction (``occ3d``)."""
    confusion = np.asarray(confusion, dtype=np.float64)
    tp = np.diag(confusion)
    gt = confusion.sum(axis=1)
    union = gt + confusion.sum(axis=0) - tp
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = tp / union
    if convention == "sparseocc":
        iou[gt == 0] = np.nan
    elif convention != "occ3d":
        raise ValueError(f"unknown mIoU convention {convention!r} "
                         f"(expected one of {', '.join(MIOU_CONVENTIONS)})")
    return iou


class MIoU:
    """Streaming voxel mIoU: ``add(pred, gt, mask)`` per sample, ``result()`` at the end.

    Only the (C+1)^2 int64 confusion is kept, so a split never needs all grids in memory.
    """

    def __init__(self, num_classes: int = NUM_OCC_CLASSES, convention: str = "sparseocc"):
        if num_classes < 1:
            raise ValueError(f"num_classes must be >= 1, got {num_classes}")
        if convention not in MIOU_CONVENTIONS:
            raise ValueError(f"unknown mIoU convention {convention!r} "
                             f"(expected one of {', '.join(MIOU_CONVENTIONS)})")
        self.convention = convention
        self.num_classes = num_classes
        self.free_label = num_classes
        self.confusion = np.zeros((num_classes + 1, num_classes + 1), dtype=np.int64)
        self.samples = 0

    def add(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> None:
        """pred, gt: int [X, Y, Z] labels 0..C (C = free); mask: bool [X, Y, Z] voxels to score
        (mask_camera), None = all voxels."""
        pred = check_labels("prediction", pred, self.free_label)
        gt = check_labels("ground truth", gt, self.free_label)
        if pred.shape != gt.shape:
            raise ValueError(f"prediction shape {pred.shape} != ground truth shape {gt.shape}")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != gt.shape:
                raise ValueError(f"mask shape {mask.shape} != ground truth shape {gt.shape}")
            pred, gt = pred[mask.astype(bool)], gt[mask.astype(bool)]
        size = self.num_classes + 1
        pairs = gt.astype(np.int64).ravel() * size + pred.astype(np.int64).ravel()
        self.confusion += np.bincount(pairs, minlength=size * size).reshape(size, size)
        self.samples += 1

    def per_class_iou(self) -> np.ndarray:
        """float64 [C]: IoU of classes 0..C-1 (NaN per the convention, module docstring)."""
        return iou_from_confusion(self.confusion, self.convention)[: self.num_classes]

    def miou(self) -> float:
        iou = self.per_class_iou()
        return float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan")

    def geometry_iou(self) -> float:
        """Occupied-vs-free IoU over the same voxels (NaN when the GT has nothing occupied)."""
        c = self.num_classes
        occupied = np.array([[self.confusion[:c, :c].sum(), self.confusion[:c, c].sum()],
                             [self.confusion[c, :c].sum(), self.confusion[c, c]]])
        return float(iou_from_confusion(occupied)[0])

    def result(self) -> dict:
        """{"mIoU", "IoU_geometry"} as fractions (0..1, NaN allowed), "per_class" [C] array,
        "samples", "convention"."""
        return {"mIoU": self.miou(), "IoU_geometry": self.geometry_iou(),
                "per_class": self.per_class_iou(), "samples": self.samples,
                "convention": self.convention}
