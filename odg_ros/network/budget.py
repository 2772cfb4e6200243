"""Query budgets: the decoder refines only the queries a scene needs.

The first ``AFTER_LAYER`` decoder layers run on every query. Then a learned keep-score ranks
the queries (static and dynamic apart) by how much the remaining layers would improve their
output, and a budget keeps the ``static`` + ``dynamic`` best of them: a fixed-size top-k
gather, so every budget is one static-shape step (one compiled graph, one CUDA graph each).
The later layers refine the kept queries only. Every other query still reaches the output:
one skip layer (decoder.SkipLayer: attention among the skipped queries, FFN, the last layer's
points and boxes, no image sampling) takes it from ``AFTER_LAYER`` straight to the output,
so the last layer always has all Q queries, in their own order, and the grid and the box list
need no change. An easy query (flat ground, empty road) thus gets three layers,
a hard one all of them.

The full budget runs the plain decoder (the skip layer is not used); its keep-scores are
still computed, so that the host can choose the next frame's budget from them
(``needed_queries``; online/budget_policy.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from .postprocess import box_list

# the budget ladder of ``query_budget: auto``: (static, dynamic) fractions of the queries,
# largest first
LADDER = ((1.0, 1.0), (0.6, 0.5), (0.35, 0.25))
AFTER_LAYER = 2            # the layers every query runs; the keep-scores rank after it
# queries are kept in multiples of this (tensor-core / vector friendly shapes)
QUERY_MULTIPLE = 4


@dataclass(frozen=True)
class QueryBudget:
    """How many static and dynamic queries the layers after ``AFTER_LAYER`` refine."""
    static: int
    dynamic: int

    @property
    def name(self) -> str:
        return f"s{self.static}-d{self.dynamic}"

    def is_full(self, num_static: int, num_dynamic: int) -> bool:
        return self.static >= num_static and self.dynamic >= num_dynamic

    def refined_fraction(self, cfg) -> float:
        """The share of the model's queries that the layers after AFTER_LAYER refine."""
        return (min(self.static, cfg.static_queries) +
                min(self.dynamic, cfg.dynamic_queries)) / cfg.num_queries

    def describe(self, cfg) -> str:
        """The budget in words, e.g. ``s120-d52: 120 of 200 (60 %) static queries, 52 of 100
        (52 %) dynamic, 57 % of all``."""
        def share(kept: int, total: int) -> str:
            kept = min(kept, total)
            return f"{kept} of {total}" + (f" ({100 * kept / total:.0f} %)" if total else "")
        if self.is_full(cfg.static_queries, cfg.dynamic_queries):
            return f"{self.name}: every query (full)"
        return (f"{self.name}: {share(self.static, cfg.static_queries)} static queries, "
                f"{share(self.dynamic, cfg.dynamic_queries)} dynamic, "
                f"{100 * self.refined_fraction(cfg):.0f} % of all")


def budget_of(cfg, static_fraction: float, dynamic_fraction: float | None = None
              ) -> QueryBudget:
    """The budget keeping these fractions of the model's static and dynamic queries (rounded
    up to a multiple of QUERY_MULTIPLE, at least one of each where the model has any)."""
    dynamic_fraction = static_fraction if dynamic_fraction is None else dynamic_fraction
    for fraction in (static_fraction, dynamic_fraction):
        if not (math.isfinite(fraction) and 0.0 < fraction <= 1.0):
            raise ValueError(f"query budget fraction {fraction}: expected 0 < fraction <= 1")
    if cfg.num_layers <= AFTER_LAYER:
        raise ValueError(f"a query budget needs more than {AFTER_LAYER} decoder layers; the "
                         f"model has {cfg.num_layers}")

    def count(total: int, fraction: float) -> int:
        if total == 0:
            return 0
        return min(total, max(1, QUERY_MULTIPLE * math.ceil(total * fraction / QUERY_MULTIPLE)))
    return QueryBudget(count(cfg.static_queries, static_fraction),
                       count(cfg.dynamic_queries, dynamic_fraction))


def budget_ladder(cfg, ladder=LADDER) -> list[QueryBudget]:
    """The budgets of ``query_budget: auto`` for this model, largest first."""
    return [budget_of(cfg, s, d) for s, d in ladder]


KEEP_INPUTS = 9          # keep_inputs' per-query values besides the feature


class KeepScore(nn.Module):
    """How much the later layers change a query's part of the grid (trained to regress that
    change, each voxel weighted by what it is worth to the keyframe's mIoU,
    ``train/budget_heads.refinement_change``), from its feature after AFTER_LAYER and
    ``keep_inputs``. One head per query set."""

    def __init__(self, embed_dims: int, hidden: int = 256):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(embed_dims + KEEP_INPUTS, hidden), nn.ReLU(),
                                 nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1))

    def forward(self, query: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        """query [B, Q, E], inputs [B, Q, KEEP_INPUTS] -> score [B, Q]."""
        return self.mlp(torch.cat([query, inputs.to(query.dtype)], dim=-1)).squeeze(-1)


def best_logits(logits: torch.Tensor, box_logits: torch.Tensor | None, num_dynamic: int):
    """Layer outputs -> (best point logit [B, Q], best box logit [B, Q]: 0 for static
    queries and where the model has no box head)."""
    point = logits.amax(dim=(2, 3))
    box = torch.zeros_like(point)
    if box_logits is not None and num_dynamic:
        box = torch.cat([box_logits.amax(dim=-1).to(point.dtype), box[:, num_dynamic:]], 1)
    return point, box


def keep_inputs(means: torch.Tensor, point: torch.Tensor, box: torch.Tensor, pc_range):
    """What the keep-scores see besides the feature: [B, Q, KEEP_INPUTS] = best point and
    box logits (``best_logits``), the centroid of the query's means (in units of the grid's
    half extent), their spread (std, m) and the centroid's horizontal distance from the ego
    (same units)."""
    centroid = means.mean(dim=2)
    spread = means.std(dim=2) if means.shape[2] > 1 else torch.zeros_like(centroid)
    # python scalars, not a new tensor: a tensor built from a list is a host -> device copy
    position = torch.stack([(centroid[..., i] - (pc_range[i + 3] + pc_range[i]) / 2)
                            / ((pc_range[i + 3] - pc_range[i]) / 2) for i in range(3)], dim=-1)
    distance = position[..., :2].norm(dim=-1, keepdim=True)
    return torch.cat([point.unsqueeze(-1), box.unsqueeze(-1), position, spread, distance],
                     dim=-1)


class BudgetHeads(nn.Module):
    """The keep-scores of both query sets and the skip layer (built by the decoder: a
    ``SkipLayer`` from AFTER_LAYER's points to the last layer's). ``trained`` and
    ``need_threshold`` (the keep-score above which a query counts as needed,
    ``needed_queries``) are saved with the weights and mirrored on the host (``is_trained``,
    ``threshold``) so that a step never reads them from the device. A checkpoint without
    these heads runs the full budget only."""

    def __init__(self, embed_dims: int, skip_layer: nn.Module):
        super().__init__()
        self.static_score = KeepScore(embed_dims)
        self.dynamic_score = KeepScore(embed_dims)
        self.skip_layer = skip_layer
        self.register_buffer("trained", torch.zeros((), dtype=torch.bool))
        self.register_buffer("need_threshold", torch.zeros(()))
        self.is_trained, self.threshold = False, 0.0

    def set_trained(self, trained: bool, need_threshold: float = 0.0) -> None:
        self.trained.fill_(bool(trained))
        self.need_threshold.fill_(float(need_threshold))
        self._mirror()

    def _mirror(self) -> None:
        self.is_trained = bool(self.trained)
        self.threshold = float(self.need_threshold)

    def _load_from_state_dict(self, *args, **kwargs):
        super()._load_from_state_dict(*args, **kwargs)
        self._mirror()                           # at load time, on the host

    def scores(self, query, means, logits, box_logits, num_dynamic: int,
               pc_range) -> torch.Tensor:
        """Keep-score of every query [B, Q] (dynamic first) from AFTER_LAYER's output."""
        point, box = best_logits(logits, box_logits, num_dynamic)
        return self.scores_of(query, keep_inputs(means, point, box, pc_range), num_dynamic)

    def scores_of(self, query, inputs, num_dynamic: int) -> torch.Tensor:
        """query [B, Q, E], inputs [B, Q, KEEP_INPUTS] (``keep_inputs``) -> [B, Q]."""
        D = num_dynamic
        static = self.static_score(query[:, D:], inputs[:, D:])
        if not D:
            return static
        return torch.cat([self.dynamic_score(query[:, :D], inputs[:, :D]), static], dim=1)


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


@torch.no_grad()
def needed_queries(scores: torch.Tensor, num_dynamic: int, threshold: float) -> torch.Tensor:
    """Queries whose keep-score says refining them changes the grid by more than ``threshold``:
    [B, 2] (static, dynamic) counts, computed on the device and read back with the outputs."""
    need = (scores > threshold).sum(dim=1)
    dynamic = (scores[:, :num_dynamic] > threshold).sum(dim=1)
    return torch.stack([need - dynamic, dynamic], dim=1)


def output_needs(output, model, cfg) -> tuple[int, int, int]:
    """What a budgeted output asks of the next step (``BudgetPolicy.update``'s arguments):
    the static and dynamic queries its keep-scores call needed and the objects it has."""
    static, dynamic = needed_queries(output.keep_scores, output.num_dynamic,
                                     model.decoder.budget_heads.threshold)[0].tolist()
    return static, dynamic, len(box_list(output, cfg)[0])
