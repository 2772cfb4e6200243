"""Query budgets: the decoder refines only the queries a scene needs.

The first ``after_layer`` decoder layers run on every query. Then a learned keep-score ranks
the queries (static and dynamic apart) by how much the remaining layers would improve their
output, and a budget keeps the ``static`` + ``dynamic`` best of them: a fixed-size top-k
gather, so every budget is one static-shape step (one compiled graph, one CUDA graph each).
The later layers refine the kept queries only. Every other query still reaches the output:
the skip head turns its feature after ``after_layer`` directly into the last layer's points
(its boxes are those of layer ``after_layer``), so the last layer always has all Q queries,
in their own order, and the grid and box list need no change.

The full budget runs the plain decoder (the skip head is not used); its keep-scores are
still computed, so that the host can choose the next frame's budget from them
(``needed_queries``; online/budget_policy.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from .gaussian_heads import PointHead

# the budget ladder of ``query_budget: auto``: (static, dynamic) fractions of the queries,
# largest first
LADDER = ((1.0, 1.0), (0.6, 0.5), (0.35, 0.25))
AFTER_LAYER = 2
# queries are kept in multiples of this (tensor-core / vector friendly shapes)
QUERY_MULTIPLE = 4


@dataclass(frozen=True)
class QueryBudget:
    """How many static and dynamic queries the layers after ``after_layer`` refine."""
    static: int
    dynamic: int
    after_layer: int = AFTER_LAYER

    @property
    def name(self) -> str:
        return f"s{self.static}-d{self.dynamic}"

    def is_full(self, num_static: int, num_dynamic: int) -> bool:
        return self.static >= num_static and self.dynamic >= num_dynamic


def budget_of(cfg, static_fraction: float, dynamic_fraction: float | None = None,
              after_layer: int = AFTER_LAYER) -> QueryBudget:
    """The budget keeping these fractions of the model's static and dynamic queries (rounded
    up to a multiple of QUERY_MULTIPLE, at least one of each where the model has any)."""
    dynamic_fraction = static_fraction if dynamic_fraction is None else dynamic_fraction
    for fraction in (static_fraction, dynamic_fraction):
        if not (math.isfinite(fraction) and 0.0 < fraction <= 1.0):
            raise ValueError(f"query budget fraction {fraction}: expected 0 < fraction <= 1")
    if not 1 <= after_layer < cfg.num_layers:
        raise ValueError(f"query budget after layer {after_layer}: the model has "
                         f"{cfg.num_layers} layers")

    def count(total: int, fraction: float) -> int:
        if total == 0:
            return 0
        return min(total, max(1, QUERY_MULTIPLE * math.ceil(total * fraction / QUERY_MULTIPLE)))
    return QueryBudget(count(cfg.static_queries, static_fraction),
                       count(cfg.dynamic_queries, dynamic_fraction), after_layer)


def budget_ladder(cfg, ladder=LADDER, after_layer: int = AFTER_LAYER) -> list[QueryBudget]:
    """The budgets of ``query_budget: auto`` for this model, largest first."""
    return [budget_of(cfg, s, d, after_layer) for s, d in ladder]


class KeepScore(nn.Module):
    """How much the later layers improve a query's output (trained to regress that gain in
    grid voxels, ``train/budget_heads.py``), from its feature after ``after_layer`` and that
    layer's best point and box logits. One head per query set."""

    def __init__(self, embed_dims: int, hidden: int = 64):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(embed_dims + 2, hidden), nn.ReLU(),
                                 nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1))

    def forward(self, query: torch.Tensor, point_logit: torch.Tensor,
                box_logit: torch.Tensor) -> torch.Tensor:
        """query [B, Q, E], point_logit, box_logit [B, Q] -> score [B, Q]."""
        extra = torch.stack([point_logit, box_logit], dim=-1).to(query.dtype)
        return self.mlp(torch.cat([query, extra], dim=-1)).squeeze(-1)


def keep_features(logits: torch.Tensor, box_logits: torch.Tensor | None, num_dynamic: int):
    """Layer outputs -> (best point logit [B, Q], best box logit [B, Q]: 0 for static
    queries and where the model has no box head)."""
    point = logits.amax(dim=(2, 3))
    box = torch.zeros_like(point)
    if box_logits is not None and num_dynamic:
        box = torch.cat([box_logits.amax(dim=-1).to(point.dtype), box[:, num_dynamic:]], 1)
    return point, box


class BudgetHeads(nn.Module):
    """The keep-scores of both query sets and the skip head (the last layer's point head
    shape, for the queries a budget does not refine). ``trained`` is saved with the weights:
    a checkpoint without these heads runs the full budget only."""

    def __init__(self, embed_dims: int, last_points: int, num_classes: int):
        super().__init__()
        self.static_score = KeepScore(embed_dims)
        self.dynamic_score = KeepScore(embed_dims)
        self.skip_points = PointHead(embed_dims, last_points, num_classes)
        # saved with the weights and mirrored on the host (``is_trained``, ``threshold``,
        # ``after_layer``), so that a step never reads them from the device: whether the heads
        # are trained, the keep-score above which a query counts as needed
        # (``needed_queries``), and the layer after which they were trained to rank
        self.register_buffer("trained", torch.zeros((), dtype=torch.bool))
        self.register_buffer("need_threshold", torch.zeros(()))
        self.register_buffer("trained_after_layer", torch.tensor(AFTER_LAYER))
        self.is_trained, self.threshold, self.after_layer = False, 0.0, AFTER_LAYER

    def set_trained(self, trained: bool, need_threshold: float = 0.0,
                    after_layer: int = AFTER_LAYER) -> None:
        self.trained.fill_(bool(trained))
        self.need_threshold.fill_(float(need_threshold))
        self.trained_after_layer.fill_(int(after_layer))
        self._mirror()

    def _mirror(self) -> None:
        self.is_trained = bool(self.trained)
        self.threshold = float(self.need_threshold)
        self.after_layer = int(self.trained_after_layer)

    def _load_from_state_dict(self, *args, **kwargs):
        super()._load_from_state_dict(*args, **kwargs)
        self._mirror()                           # at load time, on the host

    def scores(self, query, logits, box_logits, num_dynamic: int) -> torch.Tensor:
        """Keep-score of every query [B, Q] (dynamic first) from the budget layer's output."""
        point, box = keep_features(logits, box_logits, num_dynamic)
        return self.scores_of(query, point, box, num_dynamic)

    def scores_of(self, query, point, box, num_dynamic: int) -> torch.Tensor:
        """query [B, Q, E], best point / box logits [B, Q] (``keep_features``) -> [B, Q]."""
        D = num_dynamic
        static = self.static_score(query[:, D:], point[:, D:], box[:, D:])
        if not D:
            return static
        return torch.cat([self.dynamic_score(query[:, :D], point[:, :D], box[:, :D]),
                          static], dim=1)


def ranked_queries(scores: torch.Tensor, num_dynamic: int, budget: QueryBudget):
    """scores [B, Q] -> (kept [B, k_d + k_s], skipped [B, Q - k_d - k_s]) query indices, each
    dynamic first and in ascending order within a set: a fixed-size top-k per set (no
    host read; ties go to the lower index, so eager and compiled runs pick alike)."""
    D = num_dynamic
    kept, skipped = [], []
    for begin, end, keep in ((0, D, budget.dynamic), (D, scores.shape[1], budget.static)):
        if end == begin:
            continue
        keep = min(keep, end - begin)
        order = torch.sort(scores[:, begin:end], dim=1, descending=True, stable=True).indices
        kept.append(order[:, :keep].sort(dim=1).values + begin)
        skipped.append(order[:, keep:].sort(dim=1).values + begin)
    return torch.cat(kept, dim=1), torch.cat(skipped, dim=1)


def gather_queries(t: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """t [B, Q, ...], index [B, Q'] -> t[b, index[b]] [B, Q', ...] (a static-shape gather)."""
    view = index.view(*index.shape, *([1] * (t.dim() - 2)))
    return t.gather(1, view.expand(-1, -1, *t.shape[2:]))


def scatter_queries(full: torch.Tensor, index: torch.Tensor, part: torch.Tensor):
    """A copy of ``full`` [B, Q, ...] with rows ``index`` [B, Q'] replaced by ``part``."""
    view = index.view(*index.shape, *([1] * (full.dim() - 2)))
    return full.scatter(1, view.expand(-1, -1, *full.shape[2:]), part)


@torch.no_grad()
def needed_queries(scores: torch.Tensor, num_dynamic: int, threshold: float) -> torch.Tensor:
    """Queries whose keep-score says refining them gains more than ``threshold`` voxels:
    [B, 2] (static, dynamic) counts, computed on the device and read back with the outputs."""
    need = (scores > threshold).sum(dim=1)
    dynamic = (scores[:, :num_dynamic] > threshold).sum(dim=1)
    return torch.stack([need - dynamic, dynamic], dim=1)
