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


# ------------------------------------------------------------------ probabilities
# voxels sampled per keyframe for the hazard fit (among those the predicted surfaces leave
# seen), and the fewest voxels of a class for a temperature of its own
HAZARD_SAMPLES = 6000
MIN_CLASS_VOXELS = 500


@torch.enable_grad()
def fit_logistic(x: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None,
                 positive_scale: bool = True) -> tuple[float, float]:
    """(a, b) of P(y) = sigmoid(a x + b) by weighted maximum likelihood (a > 0 with
    ``positive_scale``: the map stays monotone increasing)."""
    x = torch.as_tensor(np.asarray(x, np.float64))
    y = torch.as_tensor(np.asarray(y, np.float64))
    w = torch.ones_like(x) if weight is None else torch.as_tensor(np.asarray(weight, np.float64))
    w = w / w.sum()
    raw_a = torch.tensor(0.5413, dtype=torch.float64, requires_grad=True)   # softplus -> 1
    b = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    optimiser = torch.optim.LBFGS([raw_a, b], max_iter=200, line_search_fn="strong_wolfe")

    def loss():
        optimiser.zero_grad()
        a = torch.nn.functional.softplus(raw_a) if positive_scale else raw_a
        value = (w * torch.nn.functional.binary_cross_entropy_with_logits(
            a * x + b, y, reduction="none")).sum()
        value.backward()
        return value
    optimiser.step(loss)
    a = torch.nn.functional.softplus(raw_a) if positive_scale else raw_a
    return float(a.detach()), float(b.detach())


@torch.enable_grad()
def fit_hazard(paths: np.ndarray, seen: np.ndarray, weight: np.ndarray | None = None,
               steps: int = 400) -> np.ndarray:
    """Rates lambda >= 0 [K] that make exp(-paths @ lambda) the probability that a voxel is
    seen, by maximum likelihood: paths [V, K] (each hazard's optical depth up to the voxel at
    rate 1, Visibility.optical_paths), seen bool [V] (mask_camera)."""
    L = torch.as_tensor(np.asarray(paths, np.float64))
    y = torch.as_tensor(np.asarray(seen, np.float64))
    w = torch.ones_like(y) if weight is None else torch.as_tensor(np.asarray(weight, np.float64))
    w = w / w.sum()
    raw = torch.full((L.shape[1],), -6.0, dtype=torch.float64, requires_grad=True)
    optimiser = torch.optim.Adam([raw], lr=0.05)
    for _ in range(steps):
        optimiser.zero_grad()
        depth = (L @ torch.nn.functional.softplus(raw)).clamp(min=1e-9)
        # seen: log P = -depth; hidden: log(1 - exp(-depth))
        loss = -(w * torch.where(y > 0.5, -depth, torch.log(-torch.expm1(-depth)))).sum()
        loss.backward()
        optimiser.step()
    return torch.nn.functional.softplus(raw).detach().numpy()


def visibility_curve(depth: np.ndarray, seen: np.ndarray, weights: np.ndarray,
                     visible_voxels: float) -> dict:
    """Precision and recall of "observed" per ``visibility_min_clear`` from the sampled
    voxels' optical depths (``seen``: truly visible; ``weights``: voxels each stands for)."""
    curve = {}
    for min_clear in (0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95):
        clear = depth <= (-np.log(min_clear) if min_clear > 0 else np.inf)
        true_seen, said = (weights * (clear & seen)).sum(), (weights * clear).sum()
        curve[str(min_clear)] = {"precision": round(true_seen / said, 4) if said else None,
                                 "recall": round(true_seen / visible_voxels, 4)}
    return curve


def fit_free_voxels(cfg, values: dict, kept: list, device) -> tuple[float, float]:
    """(scale, bias) of a free voxel's P(occupied) from log(hazard), with the hazard of the
    calibration ``values`` fitted so far, on the kept (grid, truth, mask) keyframes."""
    from ..network.calibration import HAZARD_FLOOR, Calibration
    free_label = cfg.num_classes
    calibration = Calibration(cfg.replace(calibration=values), device)
    edges = np.linspace(np.log(HAZARD_FLOOR), np.log(10.0), 201)
    counts = np.zeros((len(edges) + 1, 2))
    for grid, truth, mask in kept:
        _, hazard = calibration(torch.as_tensor(grid, device=device),
                                torch.zeros(len(grid), dtype=torch.uint8, device=device))
        free = mask & (grid == free_label)
        h = np.log(hazard.cpu().numpy()[free] + HAZARD_FLOOR)
        np.add.at(counts, (np.digitize(h, edges), (truth[free] != free_label).astype(int)), 1)
    centres = np.concatenate([[edges[0]], 0.5 * (edges[1:] + edges[:-1]), [edges[-1]]])
    return _fit_counts(centres, counts)


def fit_classes(label_counts: np.ndarray) -> tuple[list, list]:
    """(scale, bias) per class of an occupied voxel's P(label right) from its raw score byte,
    ``label_counts`` [C, 256, 2] (class, byte, wrong/right); a rare class takes the pooled
    fit."""
    raw_logit = logit_of_bytes()
    pooled_fit = _fit_counts(raw_logit, label_counts.sum(0))
    scale, bias = [], []
    for counts in label_counts:
        fit = _fit_counts(raw_logit, counts) \
            if counts.sum() >= MIN_CLASS_VOXELS and counts[:, 0].sum() > 0 \
            and counts[:, 1].sum() > 0 else pooled_fit
        scale.append(fit[0])
        bias.append(fit[1])
    return scale, bias


@torch.no_grad()
def fit_probabilities(model, cfg, infos_list, limit: int | None = None, device="cpu",
                      progress: bool = True, seed: int = 0) -> dict:
    """Fit ``ModelConfig.calibration`` (network/calibration.py) on training keyframes (every
    ``infos`` of the list, the first ``limit`` of each): the voxel confidence against the
    ground truth inside mask_camera, the missed-occupancy hazard against mask_camera, the box
    scores against the GT boxes. -> {"calibration": the dict, "report": what it was fitted
    on, with the visibility's precision and recall per min_clear on those keyframes}."""
    from ..metrics.planner import ConfidenceScore
    from ..network.calibration import HAZARD_RATES, hazard_indicators, rate_lengths
    from ..network.visibility import Visibility
    from .evaluate import PublishedGrid, padded_grid
    C, free_label = cfg.num_classes, cfg.num_classes
    rng = np.random.default_rng(seed)
    label_counts = np.zeros((C, 256, 2))
    paths, seen, weights, kept, boxes = [], [], [], [], ConfidenceScore(cfg.labels.names[:C])
    totals = np.zeros(2)                             # mask_camera voxels; hard-seen among them
    hard = Visibility(cfg.grid_shape, cfg.pc_range, cfg.voxel_size, free_label, 0.0,
                      device=device)
    keyframes = 0
    for infos in infos_list:
        dataset = OccDataset(infos, cfg, train=False)
        for index, batch, output in predict_split(model, dataset, limit, device,
                                                  progress=progress, desc="calibrate"):
            info = dataset.infos[index]
            add_box_sample_scores(boxes, output, batch, cfg)
            if not batch["has_occ"][0]:
                continue
            keyframes += 1
            truth = batch["occ_semantics"][0].cpu().numpy().reshape(-1)
            mask = batch["occ_mask_camera"][0].cpu().numpy().astype(bool).reshape(-1)
            labels, raw = (t.reshape(-1) for t in padded_grid(output, cfg))
            grid, raw_np = labels.cpu().numpy(), raw.cpu().numpy()
            occupied = mask & (grid != free_label)
            np.add.at(label_counts, (grid[occupied], raw_np[occupied],
                                     (grid[occupied] == truth[occupied]).astype(int)), 1)
            geometry = PublishedGrid.geometry(
                batch["ego2img"][0, 0].cpu().numpy(),
                [info["cams"][c]["image_hw"] for c in dataset.camera_names], cfg.image_size,
                device)
            observed = hard(labels, *geometry).cpu().numpy().astype(bool)
            totals += [mask.sum(), (observed & mask).sum()]
            candidates = np.flatnonzero(observed)
            voxels = rng.choice(candidates, min(HAZARD_SAMPLES, len(candidates)),
                                replace=False)
            index_tensor = torch.as_tensor(voxels, device=device)
            parts = [hard.optical_paths(hazard_indicators(labels, cfg, [name])[name],
                                        *geometry, index_tensor) for name in HAZARD_RATES]
            paths.append(torch.cat(parts, -1).cpu().numpy().astype(np.float32))
            seen.append(mask[voxels])
            weights.append(np.full(len(voxels), len(candidates) / max(len(voxels), 1)))
            kept.append((grid, truth, mask))
    if keyframes == 0:
        raise ValueError("no calibration keyframe has occupancy ground truth")
    # occupied voxels: a temperature and shift per class (pooled for the rare ones)
    scale, bias = fit_classes(label_counts)
    # the hazard
    paths, seen, weights = np.concatenate(paths), np.concatenate(seen), np.concatenate(weights)
    rates = fit_hazard(paths, seen, weights)
    values = {"label_scale": scale, "label_bias": bias, "free_scale": 1.0, "free_bias": 0.0,
              "box": None}
    start = 0
    for name, length in rate_lengths(C).items():
        values[name] = rates[start:start + length].tolist()
        start += length
    # free voxels: P(occupied) from log(hazard), on the same keyframes
    values["free_scale"], values["free_bias"] = fit_free_voxels(cfg, values, kept, device)
    box_pairs = boxes.box_pairs()
    if box_pairs is not None and 0 < box_pairs[1].sum() < len(box_pairs[1]):
        values["box"] = list(fit_logistic(logit_np(box_pairs[0]), box_pairs[1]))
    curve = visibility_curve(paths @ rates, seen, weights, totals[0])
    return {"calibration": values,
            "report": {"keyframes": keyframes, "hazard_voxels": int(len(seen)),
                       "boxes": 0 if box_pairs is None else int(len(box_pairs[1])),
                       "visibility_on_these_keyframes": curve}}


def add_box_sample_scores(score, output, batch, cfg) -> None:
    """The keyframe's boxes as the node publishes them (score above box_score_threshold),
    matched to its GT boxes, into a ConfidenceScore."""
    from ..network.postprocess import box_list
    score.add_boxes(box_list(output, cfg)[0], batch["gt_boxes"][0].cpu().numpy(),
                    batch["gt_labels"][0].cpu().numpy())


def logit_np(p: np.ndarray) -> np.ndarray:
    from ..network.calibration import SCORE_FLOOR
    p = np.clip(np.asarray(p, np.float64), SCORE_FLOOR, 1.0 - SCORE_FLOOR)
    return np.log(p) - np.log1p(-p)


def logit_of_bytes() -> np.ndarray:
    """logit of the raw score of each confidence byte 0..255 (as calibration.py reads it)."""
    return logit_np(np.arange(256) / 255.0)


def _fit_counts(x: np.ndarray, counts: np.ndarray) -> tuple[float, float]:
    """fit_logistic over binned data: x [B], counts [B, 2] (wrong, right) per bin."""
    used = counts.sum(1) > 0
    xs = np.concatenate([x[used], x[used]])
    ys = np.concatenate([np.zeros(used.sum()), np.ones(used.sum())])
    ws = np.concatenate([counts[used, 0], counts[used, 1]])
    return fit_logistic(xs[ws > 0], ys[ws > 0], ws[ws > 0])
