"""The occupancy grid's range as buffers (they follow the module's device), to map metres to
[0, 1] of the range and back. Non-persistent: checkpoints do not carry it."""
from __future__ import annotations

import torch
from torch import nn


class GridRange(nn.Module):
    def __init__(self, pc_range):
        super().__init__()
        lo = torch.tensor(pc_range[:3], dtype=torch.float32)
        self.register_buffer("lo", lo, persistent=False)
        self.register_buffer("size", torch.tensor(pc_range[3:], dtype=torch.float32) - lo,
                             persistent=False)

    def normalise(self, xyz: torch.Tensor) -> torch.Tensor:
        """[..., 3] metres -> [..., 3] fractions of the range."""
        return (xyz - self.lo) / self.size

    def metres(self, unit: torch.Tensor) -> torch.Tensor:
        """[..., 3] fractions of the range -> metres."""
        return self.lo + unit * self.size
