"""What the network returns (shared by losses, post-processing, the node)."""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch


@dataclass
class LayerOutput:
    """One decoder layer's prediction. Q = D + S queries, dynamic first; K points per query.

    means      [B, Q, K, 3]  Gaussian means, metres, current ego frame
    logits     [B, Q, K, C]  class logits (sigmoid scores, C = 17, no 'free' channel)
    scales     [B, Q, K, 3]  metres > 0
    rotations  [B, Q, K, 4]  unit quaternions (w, x, y, z)
    opacities  [B, Q, K]     in (0, 1)
    boxes      [B, D, 10]    (cx, cy, cz, log w, log l, log h, sin yaw, cos yaw, vx, vy) or None
    box_logits [B, D, 10]    box class logits (classes.BOX_CLASSES order) or None
    scales, rotations, opacities are None when the Phi MLPs were not run (inference).
    query_index [B, Q'] indices of the queries this layer ran on when a query budget left
                some to the skip layer (budget.py), else None; num_dynamic: D of this layer.
    """
    means: torch.Tensor
    logits: torch.Tensor
    scales: torch.Tensor | None
    rotations: torch.Tensor | None
    opacities: torch.Tensor | None
    boxes: torch.Tensor | None = None
    box_logits: torch.Tensor | None = None
    query_index: torch.Tensor | None = None
    num_dynamic: int | None = None


@dataclass
class ODGOutput:
    """init_means [B, Q, 1, 3]: the learnable initial points (supervised by Chamfer, Eq. 9).
    keep_scores [B, Q]: under a query budget, every query's keep-score (network/budget.py),
    else None."""
    init_means: torch.Tensor
    layers: list[LayerOutput]
    num_dynamic: int
    keep_scores: torch.Tensor | None = None

    @property
    def last(self) -> LayerOutput:
        return self.layers[-1]

    def cloned(self) -> ODGOutput:
        """A copy in memory of its own. A decoder compiled into CUDA graphs returns its
        outputs in static buffers that the next replay of any graph overwrites."""
        def own(layer: LayerOutput) -> LayerOutput:
            values = {f.name: getattr(layer, f.name) for f in fields(layer)}
            return replace(layer, **{name: value.clone() for name, value in values.items()
                                     if isinstance(value, torch.Tensor)})
        return replace(self, init_means=self.init_means.clone(),
                       layers=[own(layer) for layer in self.layers],
                       keep_scores=None if self.keep_scores is None
                       else self.keep_scores.clone())
