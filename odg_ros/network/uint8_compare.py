"""Comparisons of uint8 tensors with a number as bit operations. On the CPU (torch 2.13) a
comparison of a uint8 tensor with a number, or any comparison that broadcasts, runs element by
element, 8 to 20 times slower than an xor, clamp or maximum over the same bytes; the padding
and the visibility, which compare whole grids every step, use these instead."""
from __future__ import annotations

import torch


def is_not(values: torch.Tensor, number: int) -> torch.Tensor:
    """``values != number`` as uint8 1 or 0 (values of an integer dtype; only uint8 takes the
    fast path)."""
    if values.dtype != torch.uint8:
        return (values != number).to(torch.uint8)
    return (values ^ number).clamp_(max=1)


def uint8_equals(kinds: torch.Tensor, kind: int) -> torch.Tensor:
    """bool ``kinds == kind`` for uint8 kinds."""
    return torch.logical_not(kinds ^ kind)


def uint8_below(kinds: torch.Tensor, kind: int) -> torch.Tensor:
    """bool ``kinds < kind`` for uint8 kinds ."""
    return (kinds.clamp(max=kind) ^ kind).bool()
