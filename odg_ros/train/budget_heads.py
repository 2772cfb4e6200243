"""Training the query-budget heads (network/budget.py) of a trained model, the rest frozen.

1. ``collect``: the model at full budget over a split; per keyframe, the decoder's inputs
   (sampling layout of the frames' features, geometry), every query's state after
   AFTER_LAYER (feature, means, boxes, best point / box logits), the last layer's points,
   logits and boxes (the teacher) and the occupancy ground truth, one file per keyframe
   (the features are most of it: ~25 MB a keyframe for odg_cpu, in float16).
2. ``fit_skip_layer``: the skip layer learns the last layer's output of every query from
   its state after AFTER_LAYER (distillation, point by point and box by box; it starts as
   layer AFTER_LAYER + 1 with the last layer's point and box heads).
3. ``refinement_gain``: per query, what the later layers add over the skip layer's output,
   in class-weighted grid voxels (correct voxels gained, wrong ones avoided, in the camera
   mask; each class weighted by the inverse of its frequency, as mIoU weighs classes alike).
4. ``fit_keep_scores``: the keep-score heads regress that gain, so that a budget refines
   the queries that gain most.
Everything after ``collect`` runs on the cached keyframes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..network.budget import AFTER_LAYER, best_logits, keep_inputs

MAX_CLASS_WEIGHT = 50.0          # a class 50x rarer than the most common still counts 50x


@dataclass
class QueryState:
    """What the keep-scores see of one keyframe (kept in memory): Q queries, dynamic first."""
    query: torch.Tensor          # [Q, E] feature after AFTER_LAYER
    inputs: torch.Tensor         # [Q, KEEP_INPUTS] (network.budget.keep_inputs)


class DecoderCapture:
    """Hooks on the decoder (its inputs) and on layer AFTER_LAYER (its outputs)."""

    def __init__(self, decoder):
        self.inputs = self.after = None
        self.handles = [decoder.register_forward_pre_hook(self._inputs),
                        decoder.layers[AFTER_LAYER - 1].register_forward_hook(self._after)]

    def _inputs(self, module, args):
        self.inputs = args

    def _after(self, module, args, output):
        self.after = output

    def remove(self):
        for handle in self.handles:
            handle.remove()


def _half(t):
    return t.half() if t is not None and t.is_floating_point() else t


@torch.no_grad()
def collect(model, dataset, indices, cache_dir, progress: bool = True,
            desc: str = "collect") -> list[Path]:
    """Run ``model`` (eval, full budget) over ``dataset[indices]``; one file per keyframe in
    ``cache_dir`` (kept if it exists: a stopped pass resumes) -> the files."""
    from ..data.batch import collate, to_device
    model.eval()
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for index in tqdm(indices, desc=desc, disable=not progress):
        path = cache_dir / f"{desc}-{index:05d}.pt"
        files.append(path)
        if not path.is_file():
            batch = to_device(collate([dataset[index]]), "cpu")
            inputs = (batch["images"], batch["ego2img"], batch["ego_warp"], batch["time_delta"])
            torch.save(keyframe_record(model, inputs, batch["occ_semantics"][0],
                                       batch["occ_mask_camera"][0]), path)
    return files


@torch.no_grad()
def keyframe_record(model, inputs, semantics, mask) -> dict:
    """One keyframe (``inputs``: the model's positional inputs, batch of one; its ground
    truth ``semantics`` and camera ``mask`` [X, Y, Z]) -> what the later stages need: the
    decoder's inputs, every query's state after AFTER_LAYER, the last layer's output (the
    teacher) and the ground truth."""
    capture = DecoderCapture(model.decoder)
    try:
        output = model(*inputs)
    finally:
        capture.remove()
    _, _, _, levels, geometry = capture.inputs[:5]
    query, means, logits, boxes, box_logits = capture.after
    point, box = best_logits(logits, box_logits, model.num_dynamic)
    last = output.last
    return {"levels": [_half(level) for level in levels],
            "geometry": {k: v for k, v in geometry.items()},
            "query": query[0], "means": means[0],
            "boxes": None if boxes is None else boxes[0],
            "point_logit": point[0], "box_logit": box[0],
            "teacher": {"means": _half(last.means[0]), "logits": _half(last.logits[0]),
                        "boxes": None if last.boxes is None else last.boxes[0],
                        "box_logits": None if last.box_logits is None
                        else last.box_logits[0]},
            "semantics": semantics, "mask": mask}


def load_keyframe(path) -> dict:
    record = torch.load(path, weights_only=False)
    record["levels"] = [level.float() for level in record["levels"]]
    return record


def init_skip_layer(model) -> None:
    """The skip layer starts as layer AFTER_LAYER + 1 (whose input it takes) with the last
    layer's point and box heads (whose output it gives)."""
    layers, skip = model.decoder.layers, model.decoder.budget_heads.skip_layer
    skip.load_state_dict({k: v for k, v in layers[AFTER_LAYER].state_dict().items()
                          if not k.startswith("points.")}, strict=False)
    skip.points.load_state_dict(layers[-1].points.state_dict())
    if skip.boxes is not None:
        skip.boxes.load_state_dict(layers[-1].boxes.state_dict())


def skip_layer_output(model, record: dict, queries: torch.Tensor | None = None):
    """The skip layer over the cached keyframe's queries (``queries`` [Q''] indices, dynamic
    first; default all) -> (means, logits, boxes, box_logits) without the batch axis."""
    decoder, cfg = model.decoder, model.cfg
    D = model.num_dynamic
    query, means, boxes = record["query"], record["means"], record["boxes"]
    if queries is not None:
        query, means = query[queries], means[queries]
        D = int((queries < model.num_dynamic).sum())
        boxes = None if boxes is None else boxes[queries[:D]]
    geometry = record["geometry"]
    _, means, logits, boxes, box_logits = decoder.budget_heads.skip_layer(
        query[None], means[None], None if boxes is None else boxes[None], D, geometry,
        record["levels"], velocity_warp=cfg.motion_compensation,
        ego_warp=cfg.ego_compensation)
    return (means[0], logits[0], None if boxes is None else boxes[0],
            None if box_logits is None else box_logits[0])


def distillation_loss(output, teacher: dict, queries: torch.Tensor | None = None
                      ) -> torch.Tensor:
    """Point by point: the teacher's means (smooth L1, weighted by the teacher's score, so
    the points that reach the grid count most) and class probabilities (soft BCE); box by
    box: the box code (L1) and the box class probabilities (soft BCE)."""
    means, logits, boxes, box_logits = output
    t_means, t_logits = teacher["means"].float(), teacher["logits"].float()
    t_boxes, t_box_logits = teacher["boxes"], teacher["box_logits"]
    if queries is not None:
        t_means, t_logits = t_means[queries], t_logits[queries]
        if t_boxes is not None:
            dynamic = queries[queries < len(t_boxes)]
            t_boxes, t_box_logits = t_boxes[dynamic], t_box_logits[dynamic]
    target = t_logits.sigmoid()
    weight = target.amax(dim=-1) + 0.05                                   # [Q, K]
    position = (F.smooth_l1_loss(means, t_means, reduction="none", beta=0.4).sum(-1)
                * weight).sum() / weight.sum()
    loss = position + 10.0 * F.binary_cross_entropy_with_logits(logits, target)
    if boxes is not None and len(boxes):
        loss = loss + 0.25 * F.l1_loss(boxes, t_boxes) + \
            2.0 * F.binary_cross_entropy_with_logits(box_logits, t_box_logits.sigmoid())
    return loss


def _train_step(optimizer, schedule, loss: torch.Tensor) -> float:
    """One optimiser and schedule step on ``loss`` -> its value."""
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    schedule.step()
    return float(loss.detach())

def fit_skip_layer(model, files: list[Path], epochs: int = 20, lr: float = 1e-3,
                   seed: int = 0, progress: bool = True, log=None) -> list[float]:
    """Distil the last layer's output into the skip layer over the cached keyframes (one
    keyframe a step, every query) -> mean loss per epoch."""
    skip = model.decoder.budget_heads.skip_layer
    skip.eval().requires_grad_(True)          # no dropout: it distils a deterministic map
    optimizer = torch.optim.AdamW(skip.parameters(), lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, lr,
                                                   total_steps=epochs * len(files))
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for epoch in range(epochs):
        total = []
        order = torch.randperm(len(files), generator=generator).tolist()
        for i in tqdm(order, desc=f"skip layer {epoch + 1}/{epochs}", disable=not progress):
            record = load_keyframe(files[i])
            loss = distillation_loss(skip_layer_output(model, record), record["teacher"])
            total.append(_train_step(optimizer, schedule, loss))
        losses.append(float(np.mean(total)))
        if log is not None:
            log(f"skip layer epoch {epoch + 1}/{epochs}: loss {losses[-1]:.4f}")
    skip.eval().requires_grad_(False)
    return losses


def class_weights(files: list[Path], num_classes: int) -> torch.Tensor:
    """[C] per-voxel weight of each class: the inverse of its voxels in the camera mask,
    relative to the most common class, at most MAX_CLASS_WEIGHT; mean 1 over classes."""
    counts = torch.zeros(num_classes, dtype=torch.float64)
    for path in files:
        record = torch.load(path, weights_only=False)
        labels = record["semantics"][record["mask"].bool()].long()
        counts += torch.bincount(labels[labels < num_classes], minlength=num_classes).double()
    counts = counts.clamp(min=counts.max() / MAX_CLASS_WEIGHT)
    weights = counts.max() / counts
    return (weights / weights.mean()).float()


def voxel_value(means, logits, semantics, mask, weights, cfg) -> torch.Tensor:
    """What each query's points are worth to the grid: [Q] the sum over the distinct
    (voxel, class) pairs it predicts inside the camera mask (points as the grid keeps them:
    score > threshold, within max_distance_to_centroid, inside the grid) of +w_c where the
    ground truth is c, and -w_c (a false positive) - w_g (a missed class g, if occupied)
    where it is not."""
    means, scores = means.float(), logits.float().sigmoid()
    Q, K, C = scores.shape
    X, Y, Z = cfg.grid_shape
    best, label = scores.max(dim=-1)
    keep = (best > cfg.score_threshold) & torch.isfinite(means).all(-1)
    keep &= (means - means.mean(dim=1, keepdim=True)).norm(dim=-1) <= \
        cfg.max_distance_to_centroid
    index = []
    for axis, size in enumerate((X, Y, Z)):
        i = torch.floor((means[..., axis] - cfg.pc_range[axis]) / cfg.voxel_size)
        keep &= (i >= 0) & (i < size)
        index.append(i.clamp(0, size - 1).long())
    voxel = (index[0] * Y + index[1]) * Z + index[2]
    keep &= mask.bool().reshape(-1)[voxel]
    query = torch.arange(Q).unsqueeze(1).expand(Q, K)
    pairs = torch.unique((query[keep] * (X * Y * Z) + voxel[keep]) * C + label[keep])
    label, voxel, query = pairs % C, (pairs // C) % (X * Y * Z), pairs // (C * X * Y * Z)
    truth = semantics.reshape(-1)[voxel].long()
    occupied = truth < C
    missed = torch.where(occupied, weights[truth.clamp(max=C - 1)], torch.zeros(()))
    value = torch.where(truth == label, weights[label], -weights[label] - missed)
    return torch.zeros(Q).index_add_(0, query, value)


@torch.no_grad()
def refinement_gain(model, files: list[Path], weights, progress: bool = True):
    """Per keyframe: ([Q] voxel_value of the last layer's points minus the skip layer's,
    its QueryState)."""
    cfg = model.cfg
    gains, states = [], []
    for path in tqdm(files, desc="gains", disable=not progress):
        record = load_keyframe(path)
        means, logits, _, _ = skip_layer_output(model, record)
        teacher = record["teacher"]
        full = voxel_value(teacher["means"], teacher["logits"], record["semantics"],
                           record["mask"], weights, cfg)
        skip = voxel_value(means, logits, record["semantics"], record["mask"], weights, cfg)
        gains.append(full - skip)
        inputs = keep_inputs(record["means"][None], record["point_logit"][None],
                             record["box_logit"][None], cfg.pc_range)[0]
        states.append(QueryState(record["query"], inputs))
    return gains, states


def squashed(gain: torch.Tensor) -> torch.Tensor:
    """The regression target: sign(g) log(1 + |g|), so a few huge gains do not dominate."""
    return gain.sign() * gain.abs().log1p()


def fit_keep_scores(model, states: list[QueryState], gains: list[torch.Tensor],
                    epochs: int = 40, lr: float = 2e-3, keyframes_per_step: int = 8,
                    seed: int = 0, progress: bool = True, log=None) -> list[float]:
    """The static and dynamic keep-score heads regress the squashed gain of their queries."""
    heads = model.decoder.budget_heads
    D = model.num_dynamic
    modules = [heads.static_score] + ([heads.dynamic_score] if D else [])
    params = [p for m in modules for p in m.parameters()]
    for m in modules:
        m.train().requires_grad_(True)
    optimizer = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    steps = epochs * math.ceil(len(states) / keyframes_per_step)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, lr, total_steps=steps)
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for epoch in tqdm(range(epochs), desc="keep-scores", disable=not progress):
        total = []
        order = torch.randperm(len(states), generator=generator).tolist()
        for start in range(0, len(order), keyframes_per_step):
            group = order[start:start + keyframes_per_step]
            query = torch.stack([states[i].query for i in group])
            inputs = torch.stack([states[i].inputs for i in group])
            target = squashed(torch.stack([gains[i] for i in group]))
            loss = F.mse_loss(heads.scores_of(query, inputs, D), target)
            total.append(_train_step(optimizer, schedule, loss))
        losses.append(float(np.mean(total)))
        if log is not None:
            log(f"keep-scores epoch {epoch + 1}/{epochs}: loss {losses[-1]:.4f}")
    for m in modules:
        m.eval().requires_grad_(False)
    return losses
