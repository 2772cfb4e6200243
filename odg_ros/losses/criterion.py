"""The training objective of ODG (paper Sec. 3.5):

    L = L_occ + lambda_3d * L_box + sum_l lambda_l * (L_depth,l + L_sem,l)
    L_occ = CD(initial points) + sum_l [CD_l + Focal_l]          (chamfer.py)
    L_box = sum_l [L1_l + Focal_l]                                (box.py, matcher.py)
    lambda_3d = 0.2; lambda_l = 0.05 for l in {1, L}, 0.01 otherwise (render_loss.py)

Every term is returned on its own, with the loss weight of its definition inside (Chamfer 0.5,
point focal 2.0, box L1 0.25, box focal 2.0) but without lambda_3d / lambda_l, which only enter
the total ``loss``. Names: occ_chamfer_l0 (initial points), occ_chamfer_l{1..L},
occ_focal_l{l}, box_l1_l{l}, box_focal_l{l}, render_depth_l{l}, render_sem_l{l}.
"""
from __future__ import annotations

import logging
from typing import Callable

import torch

from ..config import ModelConfig
from .box import box_loss
from .chamfer import occupancy_loss, occupancy_target
from .render_loss import render_layer_weights, render_loss, sample_render_targets

log = logging.getLogger(__name__)

LAMBDA_3D = 0.2
DEFAULT_RENDER_PIXELS = 512


class ODGCriterion:
    """Loss of an ODGOutput against a collated batch (odg_ros/data/batch.py).

    cfg: the model config (grid, classes, number of layers; ``dual_queries`` False -> no box loss).
    render: False for the ablation "without rendering supervision".
    render_pixels_per_camera: supervised LiDAR pixels per camera and call (random, seeded);
        <= 0 uses all of them.
    renderer: a callable with the signature of ``odg_ros.render.render_cameras`` (the default).
    nn_method: nearest-neighbour search of the Chamfer loss ("auto", "kdtree", "cdist").

    After each call ``last_stats`` holds counts worth logging (samples without occupied voxel,
    matched boxes, NaN/inf matching costs replaced, GT velocity entries ignored, rendered pixels).
    A non-finite term raises FloatingPointError naming it, so a bad step never passes silently.
    """

    def __init__(self, cfg: ModelConfig, render: bool = True,
                 render_pixels_per_camera: int = DEFAULT_RENDER_PIXELS, seed: int = 0,
                 renderer: Callable | None = None, nn_method: str = "auto"):
        self.cfg = cfg
        self.use_boxes = cfg.dual_queries
        self.use_render = render
        self.render_pixels_per_camera = render_pixels_per_camera
        self.renderer = renderer
        self.nn_method = nn_method
        self.lambda_3d = LAMBDA_3D
        self.render_weights = render_layer_weights(cfg.num_layers)
        self.generator = torch.Generator().manual_seed(seed)
        self.last_stats: dict[str, int] = {}

    def __call__(self, output, batch: dict) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        if len(output.layers) != cfg.num_layers:
            raise ValueError(f"output has {len(output.layers)} layers, config {cfg.num_layers}")
        semantics, mask_camera = batch["occ_semantics"], batch["occ_mask_camera"]
        B = semantics.shape[0]
        device = output.init_means.device
        targets = [occupancy_target(semantics[b].to(device), mask_camera[b].to(device),
                                    cfg.pc_range, cfg.voxel_size, free_label=cfg.free_label,
                                    method=self.nn_method)
                   for b in range(B)]
        stats = {"samples_without_occ_gt": sum(t.num == 0 for t in targets),
                 "boxes_matched": 0, "nonfinite_match_costs": 0, "nonfinite_box_targets": 0,
                 "render_pixels": 0, "render_labelled_pixels": 0}
        if self.use_render:
            render_targets = sample_render_targets(batch["render_targets"],
                                                   self.render_pixels_per_camera, self.generator)
            cam_from_ego = batch["cam_from_ego"].to(device)
            intrinsics = batch["intrinsics"].to(device)

        losses: dict[str, torch.Tensor] = {}
        _require_finite("occ_chamfer_l0", init_means=output.init_means)
        init = occupancy_loss(output.init_means.reshape(B, -1, 3), None, targets, cfg.pc_range)
        losses["occ_chamfer_l0"] = init.chamfer
        total = init.chamfer
        for l, layer in enumerate(output.layers, start=1):
            means = layer.means.reshape(B, -1, 3)
            logits = layer.logits.reshape(B, means.shape[1], -1)
            _require_finite(f"occ_chamfer_l{l}", means=means)
            occ = occupancy_loss(means, logits, targets, cfg.pc_range,
                                 class_weights=cfg.labels.class_weights)
            losses[f"occ_chamfer_l{l}"], losses[f"occ_focal_l{l}"] = occ.chamfer, occ.focal
            total = total + occ.chamfer + occ.focal

            if self.use_boxes:
                if layer.boxes is None or layer.box_logits is None:
                    raise ValueError(f"layer {l} has no boxes but cfg.dual_queries is True")
                box = box_loss(layer.boxes, layer.box_logits, batch["gt_boxes"], batch["gt_labels"])
                losses[f"box_l1_l{l}"], losses[f"box_focal_l{l}"] = box.l1, box.focal
                total = total + self.lambda_3d * (box.l1 + box.focal)
                stats["boxes_matched"] += box.num_matched
                stats["nonfinite_match_costs"] += box.num_nonfinite_costs
                stats["nonfinite_box_targets"] += box.num_nonfinite_targets

            if self.use_render:
                if layer.scales is None or layer.rotations is None or layer.opacities is None:
                    raise ValueError(f"layer {l} has no scales/rotations/opacities (Phi MLPs not "
                                     "run); the rendering loss needs them")
                G = means.shape[1]
                _require_finite(f"render_depth_l{l}", scales=layer.scales,
                                rotations=layer.rotations, opacities=layer.opacities)
                ren = render_loss(means, layer.scales.reshape(B, G, 3),
                                  layer.rotations.reshape(B, G, 4),
                                  layer.opacities.reshape(B, G), logits, render_targets,
                                  cam_from_ego, intrinsics, cfg.image_size, self.renderer)
                losses[f"render_depth_l{l}"], losses[f"render_sem_l{l}"] = ren.depth, ren.semantic
                total = total + self.render_weights[l - 1] * (ren.depth + ren.semantic)
                stats["render_pixels"] += ren.num_pixels
                stats["render_labelled_pixels"] += ren.num_labelled

        bad = [name for name, value in losses.items() if not torch.isfinite(value).all()]
        if bad:
            raise FloatingPointError(f"non-finite loss terms: {', '.join(bad)}")
        losses["loss"] = total
        if stats["nonfinite_match_costs"]:
            log.warning("%d NaN/inf box matching costs replaced this step",
                        stats["nonfinite_match_costs"])
        self.last_stats = stats
        return losses


def _require_finite(term: str, **outputs: torch.Tensor) -> None:
    """Non-finite network outputs (a diverging step) cannot be searched for neighbours or
    rendered: raise the criterion's FloatingPointError naming the term (the trainer skips
    and counts the step), not the ValueError those functions keep for bad input."""
    bad = [name for name, t in outputs.items() if not bool(torch.isfinite(t).all())]
    if bad:
        raise FloatingPointError(f"non-finite loss terms: {term} (non-finite network output "
                                 f"{', '.join(bad)})")
