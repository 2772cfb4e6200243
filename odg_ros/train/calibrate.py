"""Pick the score thresholds of a trained checkpoint on a calibration split.

The grid keeps a Gaussian point when its best class probability exceeds ``score_threshold``
(postprocess.occupancy_grid). The paper's 0.5 fits a model trained to convergence; a model
trained for less sits lower, so the threshold is chosen where the camera-mask mIoU on a
calibration split (training keyframes, never the split that is reported) is best. The
network runs once per keyframe; every threshold re-uses that output.

The box score threshold (which dynamic-query boxes the node publishes) is chosen on the same
pass where F1 is best (right class within 2 m, ``DetectionScore.best_f1_threshold``); a model
whose boxes find nothing gets 1.0: it publishes no boxes instead of noise.
"""
from __future__ import annotations

import numpy as np
import torch

from ..data.dataset import OccDataset
from ..metrics.detection import DetectionScore
from ..metrics.score import OccScore
from .evaluate import add_box_sample, predict_split, predicted_grid

DEFAULT_THRESHOLDS = tuple(round(float(t), 2) for t in np.arange(0.05, 0.951, 0.05))


@torch.no_grad()
def calibrate_thresholds(model, cfg, infos, thresholds=DEFAULT_THRESHOLDS,
                         limit: int | None = None, device="cpu", progress: bool = True) -> dict:
    """-> {"best": threshold, "mIoU": {threshold: mIoU in percent}, "samples": n, "box":
    best_f1_threshold() or None without dynamic queries}.

    Ties go to the higher threshold (fewer points, a cheaper grid). Raises ValueError when
    no calibration keyframe has occupancy ground truth."""
    if not thresholds:
        raise ValueError("no thresholds to try")
    dataset = OccDataset(infos, cfg, train=False)
    scores = {float(t): OccScore(dataset.dataset, rayiou=False) for t in thresholds}
    boxes = DetectionScore() if cfg.dynamic_queries else None
    used = 0
    for _, batch, output in predict_split(model, dataset, limit, device, progress=progress,
                                          desc="calibrate"):
        if boxes is not None:
            add_box_sample(boxes, output, batch, cfg)
        if not batch["has_occ"][0]:
            continue
        gt = batch["occ_semantics"][0].cpu().numpy()
        mask = batch["occ_mask_camera"][0].cpu().numpy().astype(bool)
        for threshold, score in scores.items():
            score.add(predicted_grid(output, cfg.replace(score_threshold=threshold)), gt, mask)
        used += 1
    if used == 0:
        raise ValueError("no calibration keyframe has occupancy ground truth")
    miou = {t: (s.result()["mIoU"] or 0.0) for t, s in scores.items()}
    best = max(sorted(miou, reverse=True), key=lambda t: miou[t])
    return {"best": best, "mIoU": miou, "samples": used,
            "box": boxes.best_f1_threshold() if boxes is not None else None}
