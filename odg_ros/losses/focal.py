"""Sigmoid focal loss (Lin et al. 2017), the classification loss of points and boxes.

    p   = sigmoid(x)
    p_t = (1 - p) * t + p * (1 - t)            # probability of the *wrong* answer
    a_t = alpha * t + (1 - alpha) * (1 - t)
    FL  = BCE_with_logits(x, t) * a_t * p_t ** gamma

This is the mmdet formula OPUS and SparseBEV train with (gamma 2, alpha 0.25). The loss is
returned per element so each caller applies its own weights and normaliser.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

FOCAL_ALPHA = 0.25
FOCAL_GAMMA = 2.0


def sigmoid_focal_loss(logits: torch.Tensor, targets: torch.Tensor,
                       alpha: float = FOCAL_ALPHA, gamma: float = FOCAL_GAMMA) -> torch.Tensor:
    """Element-wise focal loss.

    logits  [..., C] raw scores; targets [..., C] in [0, 1] (one-hot rows, all-zero = background).
    Returns [..., C]. Finite for any finite logits (|x| = 100 included): the BCE term uses the
    log-sum-exp form and 1 - p is computed as sigmoid(-x), not by subtraction.
    """
    if logits.shape != targets.shape:
        raise ValueError(f"logits {tuple(logits.shape)} and targets {tuple(targets.shape)} differ")
    targets = targets.to(logits.dtype)
    p = torch.sigmoid(logits)
    one_minus_p = torch.sigmoid(-logits)
    p_t = one_minus_p * targets + p * (1 - targets)
    alpha_t = alpha * targets + (1 - alpha) * (1 - targets)
    bce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    return bce * alpha_t * p_t.pow(gamma)


def one_hot_targets(labels: torch.Tensor, num_classes: int, dtype=torch.float32) -> torch.Tensor:
    """labels [N] int, -1 (or any value outside [0, num_classes)) = background -> [N, C] 0/1."""
    classes = torch.arange(num_classes, device=labels.device)
    return (labels[:, None] == classes).to(dtype)    # background matches no class; no host sync
