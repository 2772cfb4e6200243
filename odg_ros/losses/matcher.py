"""Hungarian assignment of dynamic-query boxes to GT boxes (DETR-style set prediction).

Cost, as SparseBEV's ``HungarianAssigner3D`` with its nuScenes config (the box head ODG uses):
    C[i, j] = 2.0 * focal_cost(logits_i, label_j) + 0.25 * sum_k w_k |code_ik - gt_code_jk|
over all 10 code entries (SparseBEV passes its code weights and ``with_velo=True``), with the
mmdet ``FocalLossCost``:
    focal_cost = alpha (1-p)^gamma (-log p) - (1-alpha) p^gamma (-log(1-p)),  p = sigmoid(logit)
(computed here with log-sigmoid, so logits of +-100 stay finite). As in DETR, scipy's
``linear_sum_assignment`` solves each sample on the CPU; min(D, M) pairs come out.

GT code entries that are not finite (nuScenes boxes without a velocity annotation) add nothing
to the L1 cost. Any remaining NaN / inf cost (from a diverging prediction) is replaced by a
cost so large that every assignment of finite costs is cheaper (at least ``NONFINITE_COST``;
more when the finite costs themselves are huge, e.g. a diverging box code), counted and
logged -- never passed to scipy, which would raise.
"""
from __future__ import annotations

import logging
from typing import Sequence

import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment

from ..transfer import device_constant
from .focal import FOCAL_ALPHA, FOCAL_GAMMA

log = logging.getLogger(__name__)

MATCH_CLS_WEIGHT = 2.0
MATCH_L1_WEIGHT = 0.25
NONFINITE_COST = 1e6


def focal_match_cost(logits: torch.Tensor, labels: torch.Tensor, alpha: float = FOCAL_ALPHA,
                     gamma: float = FOCAL_GAMMA) -> torch.Tensor:
    """logits [D, C], labels [M] -> [D, M] focal classification cost (lower = better)."""
    p = torch.sigmoid(logits)
    pos = -F.logsigmoid(logits) * alpha * torch.sigmoid(-logits).pow(gamma)
    neg = -F.logsigmoid(-logits) * (1 - alpha) * p.pow(gamma)
    return pos[:, labels] - neg[:, labels]


def l1_match_cost(codes: torch.Tensor, gt_codes: torch.Tensor,
                  code_weights: Sequence[float]) -> torch.Tensor:
    """codes [D, K], gt_codes [M, K] -> [D, M] weighted L1 over the finite GT entries."""
    w = device_constant(code_weights, codes.device, codes.dtype)
    finite = torch.isfinite(gt_codes)
    diff = (codes[:, None, :] - torch.where(finite, gt_codes, 0)[None]).abs() * w
    return torch.where(finite[None], diff, 0).sum(-1)


def box_match_cost(codes: torch.Tensor, logits: torch.Tensor, gt_codes: torch.Tensor,
                   gt_labels: torch.Tensor, code_weights: Sequence[float],
                   cls_weight: float = MATCH_CLS_WEIGHT,
                   l1_weight: float = MATCH_L1_WEIGHT) -> torch.Tensor:
    """[D, M] matching cost of D predictions (codes [D, 10], logits [D, C]) against M GT."""
    return (cls_weight * focal_match_cost(logits, gt_labels)
            + l1_weight * l1_match_cost(codes, gt_codes, code_weights))


@torch.no_grad()
def hungarian_match(cost: torch.Tensor):
    """cost [D, M] -> (pred_index [K], gt_index [K], num_nonfinite), K = min(D, M).

    Non-finite costs are replaced by a cost larger than any assignment of finite costs can
    save (at least NONFINITE_COST), counted and logged."""
    if cost.dim() != 2:
        raise ValueError(f"cost must be [D, M], got {tuple(cost.shape)}")
    cost = cost.detach().double().cpu()
    empty = torch.zeros(0, dtype=torch.long)
    if cost.numel() == 0:
        return empty, empty, 0
    bad = ~torch.isfinite(cost)
    num_bad = int(bad.sum())
    if num_bad:
        # an assignment using one replaced entry (>= R + (K-1) min) must cost more than any
        # all-finite one (<= K max): R > K (max - min) + min
        replacement = NONFINITE_COST
        if num_bad < cost.numel():
            finite = cost[~bad]
            low, high = float(finite.min()), float(finite.max())
            replacement = max(NONFINITE_COST, min(cost.shape) * (high - low) + abs(low) + 1.0)
        log.warning("Hungarian matching: %d of %d costs are NaN/inf, replaced by %g",
                    num_bad, cost.numel(), replacement)
        cost = torch.where(bad, replacement, cost)
    rows, cols = linear_sum_assignment(cost.numpy())
    return torch.as_tensor(rows, dtype=torch.long), torch.as_tensor(cols, dtype=torch.long), num_bad
