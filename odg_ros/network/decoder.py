"""The ODG decoder: 6 layers T_l over the concatenated dual queries (paper Eq. 13-14).

Per layer, for queries [dynamic; static]:
1. position encoding of each query's previous means (+ the box for dynamic queries);
2. DaS attention (das_attention.py);
3. 4D sampling with the velocity warp (dynamic) and the ego warp (all) (sampling.py);
4. adaptive mixing, FFN;
5. heads: K_l new means + class logits (all), box code + box logits (dynamic);
   Phi_s / Phi_r / Phi_sigma give every Gaussian's scale, rotation and opacity.
Means and boxes are detached between layers (OPUS / SparseBEV), so each layer learns a
refinement of the previous one; the initial box is not detached (it has no other gradient).
"""
from __future__ import annotations

import torch
from torch import nn

from ..model_config import ModelConfig
from .box_head import BoxEncoder, BoxHead
from .budget import AFTER_LAYER, BudgetHeads, QueryBudget, gather_queries, ranked_queries
from .das_attention import DaSAttention
from .gaussian_heads import GaussianAttributes, PointHead
from .grid_range import GridRange
from .mixing import AdaptiveMixing
from .outputs import LayerOutput
from .sampling import SpatioTemporalSampling, sampling_centres


class PositionEncoder(nn.Module):
    """Embeds a query's previous K means (normalised to the grid range), as OPUS does."""

    def __init__(self, num_prev_points: int, embed_dims: int, pc_range):
        super().__init__()
        self.grid = GridRange(pc_range)
        self.mlp = nn.Sequential(
            nn.Linear(3 * num_prev_points, embed_dims), nn.LayerNorm(embed_dims), nn.ReLU(),
            nn.Linear(embed_dims, embed_dims), nn.LayerNorm(embed_dims), nn.ReLU())

    def forward(self, means: torch.Tensor) -> torch.Tensor:
        normalised = self.grid.normalise(means)
        return self.mlp(normalised.flatten(2))


class DecoderLayer(nn.Module):
    def __init__(self, cfg: ModelConfig, num_prev_points: int, num_points: int,
                 with_boxes: bool):
        super().__init__()
        E = cfg.embed_dims
        self.position = PositionEncoder(num_prev_points, E, cfg.pc_range)
        self.box_position = BoxEncoder(E, cfg.pc_range) if with_boxes else None
        self.attention = DaSAttention(E, cfg.num_heads, mix_sets=cfg.das_attention)
        self.sampling = SpatioTemporalSampling(E, cfg.num_groups, cfg.sampling_points,
                                               cfg.num_levels)
        self.mixing = AdaptiveMixing(E, cfg.num_groups, cfg.sampling_points * cfg.num_frames,
                                     cfg.mixing_out_points)
        self.ffn = nn.Sequential(nn.Linear(E, cfg.ffn_dims), nn.ReLU(), nn.Dropout(0.1),
                                 nn.Linear(cfg.ffn_dims, E), nn.Dropout(0.1))
        self.norm_attention = nn.LayerNorm(E)
        self.norm_mixing = nn.LayerNorm(E)
        self.norm_ffn = nn.LayerNorm(E)
        self.points = PointHead(E, num_points, cfg.num_classes)
        self.boxes = BoxHead(E, cfg.num_box_classes) if with_boxes else None

    def forward(self, query, prev_means, prev_boxes, num_dynamic, geometry, mlvl_feats,
                velocity_warp: bool, ego_warp: bool):
        """query [B, Q, E]; prev_means [B, Q, K_prev, 3]; prev_boxes [B, D, 10] | None;
        geometry: dict with ego2img [B,T,N,4,4], ego_warp [B,T,4,4], time_delta [B,T], image_hw
        (and frame_index, see ``SpatioTemporalSampling``).
        Returns the new query and (means, logits, boxes, box_logits)."""
        D = num_dynamic
        query, centroid = self._attend(query, prev_means, prev_boxes, D)
        velocity = None
        if velocity_warp and D:
            velocity = torch.zeros_like(centroid[..., :2])
            velocity = torch.cat([prev_boxes[..., 8:10], velocity[:, D:]], dim=1)
        sampled = self.sampling(query, prev_means, velocity, mlvl_feats, geometry["ego2img"],
                                geometry["ego_warp"] if ego_warp else None,
                                geometry["time_delta"], geometry["image_hw"],
                                geometry.get("frame_index"))
        query = self.norm_mixing(self.mixing(sampled, query))
        return self._outputs(query, centroid, prev_boxes, D)

    def _attend(self, query, prev_means, prev_boxes, D: int):
        """Position encoding and DaS attention -> (query, centroid of prev_means)."""
        position = self.position(prev_means)
        if self.box_position is not None and D:
            position = torch.cat([position[:, :D] + self.box_position(prev_boxes),
                                  position[:, D:]], dim=1)
        query = query + position
        centroid, _ = sampling_centres(prev_means)
        return self.norm_attention(query + self.attention(query, centroid, D)), centroid

    def _outputs(self, query, centroid, prev_boxes, D: int):
        """FFN and heads -> (query, means, logits, boxes, box_logits)."""
        query = self.norm_ffn(query + self.ffn(query))
        means, logits = self.points(query, centroid)
        boxes = box_logits = None
        if self.boxes is not None and D:
            boxes, box_logits = self.boxes(query[:, :D], prev_boxes)
        return query, means, logits, boxes, box_logits


class SkipLayer(DecoderLayer):
    """The query budget's skip layer (budget.py): a decoder layer without image sampling and
    mixing, from AFTER_LAYER's points straight to the last layer's. Sampling and mixing are
    most of a layer's time (docs/query_budget.md), so the queries a budget skips cost a
    fraction of one layer instead of a layer each."""

    def __init__(self, cfg: ModelConfig, num_prev_points: int, num_points: int,
                 with_boxes: bool):
        super().__init__(cfg, num_prev_points, num_points, with_boxes)
        self.sampling = self.mixing = self.norm_mixing = None

    def forward(self, query, prev_means, prev_boxes, num_dynamic, geometry, mlvl_feats,
                velocity_warp: bool, ego_warp: bool):
        """DecoderLayer.forward's arguments and results; geometry, mlvl_feats and the warps
        are not read."""
        query, centroid = self._attend(query, prev_means, prev_boxes, num_dynamic)
        return self._outputs(query, centroid, prev_boxes, num_dynamic)


class Decoder(nn.Module):
    def __init__(self, cfg: ModelConfig, num_dynamic: int):
        super().__init__()
        self.cfg = cfg
        self.num_dynamic = num_dynamic
        prev_points = (1,) + tuple(cfg.points_per_layer[:-1])
        self.layers = nn.ModuleList(
            DecoderLayer(cfg, k_prev, k, with_boxes=num_dynamic > 0)
            for k_prev, k in zip(prev_points, cfg.points_per_layer))
        self.attributes = GaussianAttributes(cfg.embed_dims, cfg.pc_range)
        # inference only, trained apart on a trained model (train/budget_heads.py): no
        # gradient in the model's own training
        skip_from = cfg.points_per_layer[min(AFTER_LAYER, cfg.num_layers) - 1]
        skip_layer = SkipLayer(cfg, skip_from, cfg.points_per_layer[-1],
                               with_boxes=num_dynamic > 0)
        self.budget_heads = BudgetHeads(cfg.embed_dims, skip_layer).requires_grad_(False)

    def forward(self, query, means, boxes, mlvl_feats, geometry,
                gaussian_attributes: bool = True, budget: QueryBudget | None = None):
        """gaussian_attributes: run Phi_s/r/sigma (rendering supervision needs them, the grid
        does not). budget: the queries the layers after ``budget.AFTER_LAYER`` refine
        (budget.py; None: all, no keep-scores).
        -> (layer outputs, keep-scores [B, Q] of the budget's layer or None)."""
        if budget is not None:
            self._check_budget(budget, gaussian_attributes)
        outputs = []
        num_dynamic = self.num_dynamic
        query_index = keep_scores = skipped = None
        for index, layer in enumerate(self.layers):
            # Refinements are detached between layers (OPUS/SparseBEV); the learnable
            # initial box is not, or it would get no gradient at all (the initial means
            # have their own Chamfer term).
            if boxes is not None and index > 0:
                boxes = boxes.detach()
            query, means, logits, boxes_new, box_logits = layer(
                query, means.detach(), boxes,
                num_dynamic, geometry, mlvl_feats,
                velocity_warp=self.cfg.motion_compensation, ego_warp=self.cfg.ego_compensation)
            scales = rotations = opacities = None
            if gaussian_attributes:
                scales, rotations, opacities = self.attributes(means, query)
            outputs.append(LayerOutput(means, logits, scales, rotations, opacities,
                                       boxes_new, box_logits, query_index, num_dynamic))
            boxes = boxes_new
            if budget is not None and index + 1 == AFTER_LAYER:
                keep_scores = self.budget_heads.scores(query, means, logits, box_logits,
                                                       num_dynamic, self.cfg.pc_range)
                if not budget.is_full(self.cfg.static_queries, num_dynamic):
                    query_index, skipped = ranked_queries(keep_scores, num_dynamic, budget)
                    kept_dynamic = min(budget.dynamic, num_dynamic)
                    skipped = self.skip_output(query, means, boxes, skipped,
                                               num_dynamic - kept_dynamic, geometry, mlvl_feats)
                    query, means = (gather_queries(t, query_index) for t in (query, means))
                    num_dynamic = kept_dynamic
                    if boxes is not None:
                        boxes = gather_queries(boxes, query_index[:, :num_dynamic])
        if skipped is not None:
            outputs[-1] = merged_layer(outputs[-1], query_index, skipped, self.num_dynamic)
        return outputs, keep_scores

    def _check_budget(self, budget: QueryBudget, gaussian_attributes: bool) -> None:
        if len(self.layers) <= AFTER_LAYER:
            raise ValueError(f"a query budget needs more than {AFTER_LAYER} decoder layers; "
                             f"the decoder has {len(self.layers)}")
        full = budget.is_full(self.cfg.static_queries, self.num_dynamic)
        heads = self.budget_heads
        if not full and not heads.is_trained:
            raise ValueError("this model's keep-score and skip heads are not trained: it runs "
                             "the full query budget only")
        if not full and gaussian_attributes:
            raise ValueError("a query budget is for inference: no Gaussian attributes")

    def skip_output(self, query, means, boxes, skipped, skipped_dynamic: int, geometry,
                    mlvl_feats) -> LayerOutput:
        """The skipped queries' last-layer output: the skip layer over their query, means and
        boxes after AFTER_LAYER (``skipped`` [B, Q'']: query indices, the first
        ``skipped_dynamic`` of them dynamic)."""
        if boxes is not None:
            boxes = gather_queries(boxes, skipped[:, :skipped_dynamic])
        query, means, logits, boxes, box_logits = self.budget_heads.skip_layer(
            gather_queries(query, skipped), gather_queries(means, skipped).detach(), boxes,
            skipped_dynamic, geometry, mlvl_feats,
            velocity_warp=self.cfg.motion_compensation, ego_warp=self.cfg.ego_compensation)
        return LayerOutput(means, logits, None, None, None, boxes, box_logits, skipped,
                           skipped_dynamic)


def merged_layer(refined: LayerOutput, kept: torch.Tensor, skipped: LayerOutput,
                 num_dynamic: int) -> LayerOutput:
    """The last layer over all Q queries in their own order: the refined ones (``kept``
    [B, Q']) and the skip head's (``skipped.query_index``); one static-shape gather each."""
    inverse = torch.cat([kept, skipped.query_index], dim=1).argsort(dim=1)
    means, logits = (gather_queries(torch.cat([a, b], dim=1), inverse)
                     for a, b in ((refined.means, skipped.means),
                                  (refined.logits, skipped.logits)))
    boxes = box_logits = None
    if refined.boxes is not None:
        kept_dynamic = refined.num_dynamic
        order = torch.cat([kept[:, :kept_dynamic],
                           skipped.query_index[:, :skipped.num_dynamic]], dim=1).argsort(dim=1)
        boxes, box_logits = (gather_queries(torch.cat([a, b], dim=1), order)
                             for a, b in ((refined.boxes, skipped.boxes),
                                          (refined.box_logits, skipped.box_logits)))
    return LayerOutput(means, logits, None, None, None, boxes, box_logits, None, num_dynamic)
