"""Box loss of the dynamic queries (paper Eq. 10) and the 10-d box code.

Box (GT, infos, node output): (cx, cy, cz, w, l, h, yaw, vx, vy) in the ego frame, metres,
centre = geometric centre, l along the heading.
Code (network output, loss space):
    (cx, cy, cz, log w, log l, log h, sin yaw, cos yaw, vx, vy)
As SparseBEV's ``normalize_bbox`` / DETR3D: the sizes in log, the yaw as (sin, cos), centre
and velocity as they are (metres, m/s). (SparseBEV's tensor order is cx, cy, w, l, cz, h, ...;
ours keeps x, y, z together -- same entries.)

Loss per layer, as SparseBEV's nuScenes config (whose matcher and weights ODG's box head takes):
* Hungarian matching (``matcher.py``);
* L1 on the code of matched pairs, code weights (2, 2, 1, 1, 1, 1, 1, 1, 1, 1) -- twice the
  weight on cx, cy -- loss weight 0.25, normalised by the number of matched GT in the batch,
  averaged over the DDP processes as DETR does (at least 1), so that DDP's mean of the
  processes' gradients weighs every matched box alike however the boxes fall on them;
* sigmoid focal loss (gamma 2, alpha 0.25, weight 2.0) on the box class logits, one-hot targets
  for matched predictions and all-zero targets for the rest, same normaliser.
GT code entries that are not finite (velocity missing in nuScenes) are left out of the L1 term
(SparseBEV drops the whole box there; keeping its position and size is the better use of it)
and counted. A GT box with a non-finite centre/size/yaw or a size <= 0 is bad input: ValueError.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
import torch.distributed as dist

from ..transfer import device_constant, upload
from .focal import FOCAL_ALPHA, FOCAL_GAMMA, one_hot_targets, sigmoid_focal_loss
from .matcher import box_match_cost, hungarian_match

BOX_CODE_WEIGHTS = (2.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
BOX_L1_WEIGHT = 0.25
BOX_FOCAL_WEIGHT = 2.0


def encode_boxes(boxes: torch.Tensor) -> torch.Tensor:
    """[..., 9] (cx, cy, cz, w, l, h, yaw, vx, vy) -> [..., 10] code."""
    if boxes.shape[-1] != 9:
        raise ValueError(f"boxes must be [..., 9], got {tuple(boxes.shape)}")
    yaw = boxes[..., 6:7]
    return torch.cat([boxes[..., 0:3], boxes[..., 3:6].log(), yaw.sin(), yaw.cos(),
                      boxes[..., 7:9]], dim=-1)


def decode_boxes(codes: torch.Tensor) -> torch.Tensor:
    """[..., 10] code -> [..., 9] box; yaw = atan2(sin, cos) in (-pi, pi]."""
    if codes.shape[-1] != 10:
        raise ValueError(f"box codes must be [..., 10], got {tuple(codes.shape)}")
    yaw = torch.atan2(codes[..., 6:7], codes[..., 7:8])
    return torch.cat([codes[..., 0:3], codes[..., 3:6].exp(), yaw, codes[..., 8:10]], dim=-1)


def check_gt_boxes(boxes: torch.Tensor, labels: torch.Tensor, num_classes: int) -> None:
    """Raise ValueError on GT that cannot be encoded; NaN/inf velocity is allowed. One host
    read of the values (more only to word an error)."""
    if boxes.dim() != 2 or boxes.shape[1] != 9:
        raise ValueError(f"gt_boxes must be [M, 9], got {tuple(boxes.shape)}")
    if labels.shape != (boxes.shape[0],):
        raise ValueError(f"gt_labels {tuple(labels.shape)} do not match {boxes.shape[0]} boxes")
    nonfinite, flat, unknown = torch.stack([
        ~torch.isfinite(boxes[:, :7]).all(), (boxes[:, 3:6] <= 0).any(),
        ((labels < 0) | (labels >= num_classes)).any()]).tolist()
    if nonfinite:
        raise ValueError("gt_boxes has a non-finite centre, size or yaw")
    if flat:
        raise ValueError("gt_boxes has a size <= 0")
    if unknown:
        raise ValueError(f"gt_labels outside [0, {num_classes})")


def matched_normaliser(num_matched: int, device) -> float | torch.Tensor:
    """This process's matched count, or under DDP the mean count over the processes (one
    all-reduce); at least 1."""
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return max(num_matched, 1)
    count = torch.full((), float(num_matched), device=device)     # a fill, not a copy
    dist.all_reduce(count)
    return (count / dist.get_world_size()).clamp(min=1.0)


@dataclass
class BoxMatch:
    """One sample's Hungarian matching: the matched indices on the predictions' device."""
    pred_index: torch.Tensor
    gt_index: torch.Tensor
    num_nonfinite_costs: int


def match_layers(layers: Sequence[tuple[torch.Tensor, torch.Tensor]],
                 gt_boxes: Sequence[torch.Tensor], gt_labels: Sequence[torch.Tensor],
                 code_weights: Sequence[float] = BOX_CODE_WEIGHTS) -> list[list[BoxMatch]]:
    """Hungarian matches of every layer's (codes [B, D, 10], logits [B, D, C]) to the GT.

    The GT is checked once, where it is given, every cost matrix comes to the host in one
    copy and every matched index goes back in one: the host waits for the device once, not
    once per layer and sample.
    """
    codes0, logits0 = layers[0]
    num_classes, device = logits0.shape[-1], codes0.device
    dtype = codes0.dtype if codes0.dtype == torch.float64 else torch.float32
    gt_codes, labels = [], []
    for b in range(codes0.shape[0]):
        # checked where the batch keeps the GT (the host in training): no wait for the device
        check_gt_boxes(gt_boxes[b], gt_labels[b], num_classes)
        boxes = upload(gt_boxes[b], device, dtype)
        labels.append(upload(gt_labels[b], device, torch.long))
        gt_codes.append(encode_boxes(boxes))
    parts = []
    with torch.no_grad():
        for codes, logits in layers:
            for b in range(codes.shape[0]):
                if gt_codes[b].shape[0] and codes.shape[1]:
                    cost = box_match_cost(codes[b].to(dtype), logits[b].to(dtype), gt_codes[b],
                                          labels[b], code_weights)
                    parts.append(cost.double().flatten())
        host = torch.cat(parts).cpu() if parts else torch.zeros(0, dtype=torch.float64)
    found = []                                   # per layer and sample: the host matching
    offset = 0
    for codes, _ in layers:
        for b in range(codes.shape[0]):
            d, m = codes.shape[1], gt_codes[b].shape[0]
            if not (m and d):
                found.append((empty_index(), empty_index(), 0))
                continue
            found.append(hungarian_match(host[offset:offset + d * m].view(d, m)))
            offset += d * m
    # every matched index goes up in one pinned copy (from pageable memory, each would wait)
    sizes = [int(index.numel()) for pred, gt, _ in found for index in (pred, gt)]
    indices = upload(torch.cat([index for pred, gt, _ in found for index in (pred, gt)]),
                     device).split(sizes)
    matches = [BoxMatch(indices[2 * i], indices[2 * i + 1], bad) for i, (*_, bad) in
               enumerate(found)]
    per_layer = [codes.shape[0] for codes, _ in layers]
    return [matches[sum(per_layer[:l]):sum(per_layer[:l + 1])] for l in range(len(layers))]


def empty_index() -> torch.Tensor:
    return torch.zeros(0, dtype=torch.long)


@dataclass
class BoxLossResult:
    l1: torch.Tensor            # scalar, includes BOX_L1_WEIGHT
    focal: torch.Tensor         # scalar, includes BOX_FOCAL_WEIGHT
    num_matched: int
    num_nonfinite_costs: int
    num_nonfinite_targets: int | torch.Tensor  # GT code entries left out of the L1 term (a
    #                                             device count: reading it would wait for it)


def box_loss(codes: torch.Tensor, logits: torch.Tensor, gt_boxes: Sequence[torch.Tensor],
             gt_labels: Sequence[torch.Tensor], code_weights: Sequence[float] = BOX_CODE_WEIGHTS,
             l1_weight: float = BOX_L1_WEIGHT, focal_weight: float = BOX_FOCAL_WEIGHT,
             alpha: float = FOCAL_ALPHA, gamma: float = FOCAL_GAMMA,
             matches: Sequence[BoxMatch] | None = None) -> BoxLossResult:
    """codes [B, D, 10], logits [B, D, C]; gt_boxes: B x [M_b, 9]; gt_labels: B x [M_b] int.
    ``matches``: this layer's entry of ``match_layers`` (computed here when not given)."""
    if codes.dim() != 3 or codes.shape[-1] != 10 or logits.shape[:2] != codes.shape[:2]:
        raise ValueError(f"box codes {tuple(codes.shape)} / logits {tuple(logits.shape)} "
                         "must be [B, D, 10] / [B, D, C]")
    if not len(gt_boxes) == len(gt_labels) == codes.shape[0]:
        raise ValueError("one gt_boxes and gt_labels entry per sample needed")
    if matches is None:
        matches = match_layers([(codes, logits)], gt_boxes, gt_labels, code_weights)[0]
    # half precision is computed in float32, float64 stays (for gradcheck)
    codes = codes if codes.dtype == torch.float64 else codes.float()
    logits = logits.to(codes.dtype)
    num_classes = logits.shape[-1]
    w = device_constant(code_weights, codes.device, codes.dtype)
    l1_sum = focal_sum = codes.new_zeros(())
    num_matched = num_bad_cost = num_bad_target = 0
    for b, match in enumerate(matches):
        targets = torch.zeros_like(logits[b])
        if match.pred_index.numel():
            boxes = upload(gt_boxes[b], codes.device, codes.dtype)
            labels = upload(gt_labels[b], codes.device, torch.long)
            pred_idx, gt_idx = match.pred_index, match.gt_index
            matched_gt = encode_boxes(boxes)[gt_idx]
            finite = torch.isfinite(matched_gt)
            num_bad_target = num_bad_target + (~finite).sum()     # stays on the device
            diff = (codes[b, pred_idx] - torch.where(finite, matched_gt, 0)).abs() * w
            l1_sum = l1_sum + torch.where(finite, diff, 0).sum()
            targets[pred_idx] = one_hot_targets(labels[gt_idx], num_classes, logits.dtype)
        num_matched += int(match.pred_index.numel())
        num_bad_cost += match.num_nonfinite_costs
        focal_sum = focal_sum + sigmoid_focal_loss(logits[b], targets, alpha, gamma).sum()
    norm = matched_normaliser(num_matched, codes.device)
    return BoxLossResult(l1=l1_weight * l1_sum / norm, focal=focal_weight * focal_sum / norm,
                         num_matched=num_matched, num_nonfinite_costs=num_bad_cost,
                         num_nonfinite_targets=num_bad_target)
