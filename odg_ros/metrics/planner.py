"""What a planner reads off the grid, scored against the ground truth (``odg eval``):

* **visibility**: the grid's ``observed`` against Occ3D's ``mask_camera``: precision and recall
  of "observed", and the precision (and recall) of "free and observed": a voxel published free
  and seen that is free in truth and seen by a camera (``mask_camera``). The same for the BEV
  (nav_msgs/OccupancyGrid) the node publishes: its cells 0 (free and seen), 100 (obstacle), -1
  (unknown), against the BEV built the same way (bev.bev_fields) from the ground-truth
  grid with ``mask_camera`` as its observed voxels: precision and recall of the known cells
  (not -1) and of the free cells (0).
* **confidence**: expected calibration error (ECE, 10 equal-width bins: the mean gap between
  the stated confidence and the share of right answers, weighted by the voxels in each bin) of
  the voxel confidence, inside ``mask_camera`` (where the ground truth is defined, as for
  mIoU): for occupied voxels (right = the class is right), for free ones (right = free in
  truth), and of the box scores (right = a ground-truth box of the class within 2 m,
  each taken once, in score order); with the reliability curve (per bin: mean confidence,
  share right, count).
* **stability**: how often a voxel's label flips between consecutive outputs, at the voxels
  that are static in the ground truth: the earlier keyframe's grids are carried into the later
  one's ego frame (nearest voxel centre, by the two ego poses), and a voxel counts where both
  keyframes' ground truth give it the same class, not one that moves (car, pedestrian, ...),
  and both cameras' masks see it. Flip rate = share of those voxels whose predicted label
  differs; also among those either output calls occupied.
"""
from __future__ import annotations

import numpy as np

from ..classes import OccLabels
from ..bev import bev_fields
from .detection import greedy_match

BINS = 10


def _ratio(numerator, denominator) -> float | None:
    """numerator / denominator to 6 significant digits (None for 0 / 0)."""
    return float(f"{float(numerator) / float(denominator):.6g}") if denominator else None


def bev_cells(grid: np.ndarray, observed: np.ndarray, pc_range, voxel_size: float,
              band: tuple[float, float], labels: OccLabels) -> np.ndarray:
    """int8 [Y, X] cells (100, 0, -1) of the node's BEV for a grid and its observed voxels."""
    fields = bev_fields(grid, pc_range, voxel_size, band[0], band[1], labels, observed)
    return np.frombuffer(fields["data"], np.int8).reshape(grid.shape[1], grid.shape[0])


class VisibilityScore:
    """Counts of published observed / free against the truth, for voxels and BEV cells."""

    def __init__(self):
        self.counts = np.zeros(12, np.int64)

    def add(self, grid, observed, truth, mask_camera, free_label: int, bev, truth_bev) -> None:
        """grid uint8 [X, Y, Z] (published labels), observed bool [X, Y, Z] (published),
        truth uint8 [X, Y, Z], mask_camera bool [X, Y, Z]; bev, truth_bev int8 [Y, X]
        (``bev_cells`` of the published grid and of the truth)."""
        free_seen = observed & (grid == free_label)
        truly_free_seen = mask_camera & (truth == free_label)
        known, truly_known = bev != -1, truth_bev != -1
        free, truly_free = bev == 0, truth_bev == 0
        self.counts += [(observed & mask_camera).sum(), observed.sum(), mask_camera.sum(),
                        (free_seen & truly_free_seen).sum(), free_seen.sum(),
                        truly_free_seen.sum(), (known & truly_known).sum(), known.sum(),
                        truly_known.sum(), (free & truly_free).sum(), free.sum(),
                        truly_free.sum()]

    def result(self) -> dict:
        c = self.counts
        return {"voxels": {"observed_precision": _ratio(c[0], c[1]),
                           "observed_recall": _ratio(c[0], c[2]),
                           "free_observed_precision": _ratio(c[3], c[4]),
                           "free_observed_recall": _ratio(c[3], c[5])},
                "bev": {"known_precision": _ratio(c[6], c[7]),
                        "known_recall": _ratio(c[6], c[8]),
                        "free_precision": _ratio(c[9], c[10]),
                        "free_recall": _ratio(c[9], c[11])}}


class Reliability:
    """Stated confidence against the share of right answers, in BINS equal-width bins."""

    def __init__(self):
        self.count = np.zeros(BINS, np.int64)
        self.confidence = np.zeros(BINS)
        self.right = np.zeros(BINS)

    def add(self, confidence: np.ndarray, right: np.ndarray) -> None:
        """confidence float [n] in [0, 1], right bool [n]."""
        confidence = np.asarray(confidence, np.float64).ravel()
        right = np.asarray(right, bool).ravel()
        index = np.minimum((confidence * BINS).astype(np.int64), BINS - 1)
        self.count += np.bincount(index, minlength=BINS)
        self.confidence += np.bincount(index, confidence, minlength=BINS)
        self.right += np.bincount(index, right, minlength=BINS)

    def add_bytes(self, confidence: np.ndarray, right: np.ndarray) -> None:
        """As ``add`` for uint8 confidence (0..255 = 0..1), summed per byte first (fast)."""
        confidence = np.asarray(confidence, np.uint8).ravel()
        right = np.asarray(right, bool).ravel()
        total = np.bincount(confidence, minlength=256)
        correct = np.bincount(confidence, right, minlength=256)
        value = np.arange(256) / 255.0
        index = np.minimum((value * BINS).astype(np.int64), BINS - 1)
        self.count += np.bincount(index, total, minlength=BINS).astype(np.int64)
        self.confidence += np.bincount(index, total * value, minlength=BINS)
        self.right += np.bincount(index, correct, minlength=BINS)

    def result(self) -> dict:
        n = self.count.sum()
        used = self.count > 0
        mean = np.where(used, self.confidence / np.maximum(self.count, 1), np.nan)
        accuracy = np.where(used, self.right / np.maximum(self.count, 1), np.nan)
        ece = float(np.sum(self.count[used] * np.abs(mean[used] - accuracy[used])) / n) \
            if n else None
        return {"ece": None if ece is None else round(ece, 4), "samples": int(n),
                "mean_confidence": _rounded(self.confidence.sum() / n if n else None),
                "accuracy": _rounded(self.right.sum() / n if n else None),
                "bins": {"confidence": [_rounded(v) for v in mean],
                         "accuracy": [_rounded(v) for v in accuracy],
                         "count": self.count.tolist()}}


def _rounded(value):
    return None if value is None or not np.isfinite(value) else round(float(value), 4)


class ConfidenceScore:
    """Reliability of the voxel confidence (occupied, free; per class) and box scores."""

    def __init__(self, names):
        self.names = tuple(names)
        self.occupied, self.free, self.boxes = Reliability(), Reliability(), Reliability()
        self._box_scores, self._box_right = [], []
        self.per_class = {name: Reliability() for name in self.names}

    def add(self, grid, confidence, truth, mask_camera, free_label: int) -> None:
        """grid, confidence (0..255), truth uint8 [X, Y, Z]; mask_camera bool [X, Y, Z]."""
        inside = mask_camera.ravel()
        grid, truth = grid.ravel()[inside], truth.ravel()[inside]
        confidence = confidence.ravel()[inside]
        right = grid == truth
        occupied = grid != free_label
        self.occupied.add_bytes(confidence[occupied], right[occupied])
        self.free.add_bytes(confidence[~occupied], right[~occupied])
        for label in np.unique(grid[occupied]):
            at = grid == label
            self.per_class[self.names[label]].add_bytes(confidence[at], right[at])

    def add_boxes(self, boxes: list[dict], gt_boxes: np.ndarray, gt_labels: np.ndarray,
                  distance: float = 2.0) -> None:
        """The published boxes of one keyframe (box_dicts, by score) against its GT boxes
        [M, >= 2] and labels [M]: right = matched to a GT box of its class within
        ``distance`` m (centre, bird's-eye view), each GT box taken once, in score order."""
        if not boxes:
            return
        scores = np.array([b["score"] for b in boxes])
        labels = np.array([b["label"] for b in boxes])
        centres = np.array([b["center"][:2] for b in boxes], np.float64).reshape(-1, 2)
        right = np.zeros(len(boxes), bool)
        gt_boxes = np.asarray(gt_boxes, np.float64).reshape(len(gt_labels), -1)
        for label in np.unique(labels):
            at = np.flatnonzero(labels == label)
            at = at[np.argsort(-scores[at], kind="stable")]
            right[at] = greedy_match(centres[at], gt_boxes[gt_labels == label, :2], distance)
        self.boxes.add(scores, right)
        self._box_scores.append(scores)
        self._box_right.append(right)

    def box_pairs(self):
        """(scores [n], right bool [n]) of every box added, or None without any."""
        if not self._box_scores:
            return None
        return np.concatenate(self._box_scores), np.concatenate(self._box_right)

    def result(self) -> dict:
        return {"occupied": self.occupied.result(), "free": self.free.result(),
                "boxes": self.boxes.result(),
                "per_class": {name: r.result()["ece"] for name, r in self.per_class.items()
                              if r.count.sum()}}


def carried_indices(pose_from, pose_to, grid_shape, pc_range, voxel_size: float):
    """Voxel centres of the grid at ``pose_to`` (T_global_from_ego [4, 4]) in the grid at
    ``pose_from``: (flat index into that grid [X*Y*Z], inside it bool [X*Y*Z])."""
    X, Y, Z = grid_shape
    axes = [(np.arange(n) + 0.5) * voxel_size + pc_range[a] for a, n in enumerate(grid_shape)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    to_from = np.linalg.inv(np.asarray(pose_from, np.float64)) @ np.asarray(pose_to, np.float64)
    points = centres @ to_from[:3, :3].T + to_from[:3, 3]
    index = np.floor((points - np.asarray(pc_range[:3])) / voxel_size).astype(np.int64)
    inside = np.all((index >= 0) & (index < np.array([X, Y, Z])), axis=1)
    index = np.where(inside[:, None], index, 0)
    return (index[:, 0] * Y + index[:, 1]) * Z + index[:, 2], inside


class FlipScore:
    """Label flips between consecutive outputs at voxels static in the ground truth."""

    def __init__(self, labels: OccLabels):
        self.free_label = labels.free_label
        self.moving = np.zeros(256, bool)
        self.moving[[labels.names.index(n) for n in labels.dynamic]] = True
        self.counts = np.zeros(4, np.int64)     # static, flipped, static occupied, flipped
        self.pairs = 0

    def add(self, before: dict, after: dict, grid_shape, pc_range, voxel_size) -> None:
        """Two consecutive keyframes of one drive, each {"grid", "truth" uint8 [X, Y, Z],
        "mask" bool [X, Y, Z], "pose" [4, 4]}."""
        index, inside = carried_indices(before["pose"], after["pose"], grid_shape, pc_range,
                                        voxel_size)
        truth_then = before["truth"].ravel()[index]
        truth_now = after["truth"].ravel()
        static = inside & (truth_then == truth_now) & ~self.moving[truth_now] & \
            before["mask"].ravel()[index] & after["mask"].ravel()
        then, now = before["grid"].ravel()[index][static], after["grid"].ravel()[static]
        flipped = then != now
        occupied = (then != self.free_label) | (now != self.free_label)
        self.counts += [static.sum(), flipped.sum(), occupied.sum(), (flipped & occupied).sum()]
        self.pairs += 1

    def result(self) -> dict:
        c = self.counts
        return {"flip_rate": _ratio(c[1], c[0]), "flip_rate_occupied": _ratio(c[3], c[2]),
                "static_voxels": int(c[0]), "pairs": self.pairs}


def format_planner(result: dict) -> str:
    """The planner's view of an ``odg eval`` result (one split, or per set and overall):
    visibility against mask_camera beside the ground-truth grid's ceiling, calibration error,
    label flips."""
    sets = dict(result.get("sets", {}))
    rows = list(sets.items()) + [("all" if sets else "split", result)]
    width = max(len(name) for name, _ in rows + [("set", None)])
    cell = lambda v: "    -" if v is None else f"{v:5.3f}"  # noqa: E731
    vis = result["visibility"]
    lines = [f"what a planner reads (against mask_camera; visibility_min_clear "
             f"{vis['min_clear']}; 'truth grid': the same from the ground-truth grid, the "
             "method's ceiling)",
             f"{'set':<{width}}  {'observed P / R':>14}  {'free+obs P':>10}  "
             f"{'BEV known P / R':>15}  {'BEV free P':>10}  |  truth grid: {'observed P / R':>14}"
             f"  {'free+obs P':>10}  {'BEV free P':>10}"]
    for name, r in rows:
        m, t = r["visibility"]["model"], r["visibility"]["ground_truth_grid"]
        lines.append(
            f"{name:<{width}}  {cell(m['voxels']['observed_precision'])} / "
            f"{cell(m['voxels']['observed_recall'])}     "
            f"{cell(m['voxels']['free_observed_precision'])}    "
            f"{cell(m['bev']['known_precision'])} / {cell(m['bev']['known_recall'])}       "
            f"{cell(m['bev']['free_precision'])}  |              "
            f"{cell(t['voxels']['observed_precision'])} / "
            f"{cell(t['voxels']['observed_recall'])}       "
            f"{cell(t['voxels']['free_observed_precision'])}       "
            f"{cell(t['bev']['free_precision'])}")
    calibrated = "calibrated" if result["confidence"]["calibrated"] else \
        "raw scores: the checkpoint has no calibration"
    lines.append(f"confidence ({calibrated}): expected calibration error")
    lines.append(f"{'set':<{width}}  {'occupied':>8}  {'free':>8}  {'boxes':>8}  "
                 f"{'flips':>8}  {'flips occ':>9}")
    for name, r in rows:
        c, f = r["confidence"], r["stability"]
        lines.append(f"{name:<{width}}  {cell(c['occupied']['ece']):>8}  "
                     f"{cell(c['free']['ece']):>8}  {cell(c['boxes']['ece']):>8}  "
                     f"{cell(f['flip_rate']):>8}  {cell(f['flip_rate_occupied']):>9}")
    lines.append("flips: share of the voxels static in the ground truth whose label changes "
                 "between consecutive keyframes ('occ': of those either output calls occupied)")
    return "\n".join(lines)
