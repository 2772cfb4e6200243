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

from ..model_config import ModelConfig
from ..training_phases import training_phase
from ..transfer import upload
from .box import box_loss, match_layers, matched_normaliser
from .chamfer import occupancy_loss, occupancy_target
from .render_loss import (NONFINITE_TARGET, render_layer_weights, render_losses,
                          sample_render_targets)

log = logging.getLogger(__name__)

LAMBDA_3D = 0.2
DEFAULT_RENDER_PIXELS = 512


class ODGCriterion:
    """Loss of an ODGOutput against a collated batch (odg_ros/data/batch.py).

    cfg: the model config (grid, classes, number of layers; ``dual_queries`` False -> no box loss).
    render: False for the ablation "without rendering supervision".
    render_pixels_per_camera: supervised LiDAR pixels per camera and call (random, seeded);
        <= 0 uses all of them.
    renderer: the render loss's renderer, called once for every layer and sample: None for
        ours (``render_scenes``), or a callable with its signature (gsplat's:
        ``render.gsplat_backend.render_scenes_gsplat``).
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
        if len(output.layers) != self.cfg.num_layers:
            raise ValueError(f"output has {len(output.layers)} layers, config "
                             f"{self.cfg.num_layers}")
        device = output.init_means.device
        targets = self._occupancy_targets(batch, device)
        stats = {"samples_without_occ_gt": sum(t.num == 0 for t in targets),
                 "boxes_matched": 0, "nonfinite_match_costs": 0, "nonfinite_box_targets": 0,
                 "render_pixels": 0, "render_labelled_pixels": 0}
        if self.use_render:
            with training_phase("render"):
                render_inputs = self._render_inputs(batch, device)
        self._check_outputs(output, device)
        boxes = self._match_boxes(output, batch, device) if self.use_boxes else None
        rendered, targets_finite = None, torch.ones((), dtype=torch.bool, device=device)
        if self.use_render:
            with training_phase("render"):
                rendered, targets_finite = self._render(output, *render_inputs)
        losses = self._layer_losses(output, targets, boxes, rendered, stats)
        self._check_losses(losses, targets_finite, stats)
        self.last_stats = stats
        return losses

    def _occupancy_targets(self, batch: dict, device) -> list:
        """Every sample's occupied voxels: checked and extracted where the batch keeps the
        grids (the host in training, where their number is known without waiting), then
        uploaded."""
        cfg = self.cfg
        semantics, mask_camera = batch["occ_semantics"], batch["occ_mask_camera"]
        return [occupancy_target(semantics[b], mask_camera[b], cfg.pc_range, cfg.voxel_size,
                                 free_label=cfg.free_label, method=self.nn_method).to(device)
                for b in range(semantics.shape[0])]

    def _render_inputs(self, batch: dict, device):
        """(the LiDAR pixels kept, cam_from_ego, intrinsics) of the render loss."""
        render_targets = sample_render_targets(batch["render_targets"],
                                               self.render_pixels_per_camera, self.generator)
        return render_targets, batch["cam_from_ego"].to(device), batch["intrinsics"].to(device)

    def _check_outputs(self, output, device) -> None:
        """One read checks every network output before any loss (the FloatingPointError of
        _require_finite)."""
        try:
            _require_finite(network_outputs(output))
        except FloatingPointError:
            if self.use_boxes:
                # under DDP the other processes go on into the box losses' all-reduces; this
                # one joins them (with no matches) so that no process waits forever
                for _ in output.layers:
                    matched_normaliser(0, device)
            raise

    def _match_boxes(self, output, batch: dict, device):
        """(every layer's Hungarian matches, the GT boxes and labels on the device)."""
        for l, layer in enumerate(output.layers, start=1):
            if layer.boxes is None or layer.box_logits is None:
                raise ValueError(f"layer {l} has no boxes but cfg.dual_queries is True")
        matches = match_layers([(layer.boxes, layer.box_logits) for layer in output.layers],
                               batch["gt_boxes"], batch["gt_labels"])
        # uploaded once for the six layers' box losses (the matching reads the host copy)
        gt_boxes = [upload(b, device) for b in batch["gt_boxes"]]
        gt_labels = [upload(b, device) for b in batch["gt_labels"]]
        return matches, gt_boxes, gt_labels

    def _render(self, output, render_targets, cam_from_ego, intrinsics):
        """(every layer's RenderLossResult, the render targets' finiteness flag): every
        layer in one renderer call, so that its reads of sizes are paid once per step."""
        B = len(render_targets)
        render_layers = []
        for l, layer in enumerate(output.layers, start=1):
            if layer.scales is None or layer.rotations is None or layer.opacities is None:
                raise ValueError(f"layer {l} has no scales/rotations/opacities (Phi MLPs not "
                                 "run); the rendering loss needs them")
            means = layer.means.reshape(B, -1, 3)
            G = means.shape[1]
            render_layers.append((means, layer.scales.reshape(B, G, 3),
                                  layer.rotations.reshape(B, G, 4),
                                  layer.opacities.reshape(B, G),
                                  layer.logits.reshape(B, G, -1)))
        return render_losses(render_layers, render_targets, cam_from_ego, intrinsics,
                             self.cfg.image_size, self.renderer)

    def _layer_losses(self, output, targets, boxes, rendered, stats: dict) -> dict:
        """Every term of every layer and their weighted total ``loss``; counts into stats."""
        cfg, B = self.cfg, len(targets)
        losses: dict[str, torch.Tensor] = {}
        init = occupancy_loss(output.init_means.reshape(B, -1, 3), None, targets, cfg.pc_range)
        losses["occ_chamfer_l0"] = init.chamfer
        total = init.chamfer
        for l, layer in enumerate(output.layers, start=1):
            means = layer.means.reshape(B, -1, 3)
            logits = layer.logits.reshape(B, means.shape[1], -1)
            occ = occupancy_loss(means, logits, targets, cfg.pc_range,
                                 class_weights=cfg.labels.class_weights)
            losses[f"occ_chamfer_l{l}"], losses[f"occ_focal_l{l}"] = occ.chamfer, occ.focal
            total = total + occ.chamfer + occ.focal

            if boxes is not None:
                matches, gt_boxes, gt_labels = boxes
                box = box_loss(layer.boxes, layer.box_logits, gt_boxes, gt_labels,
                               matches=matches[l - 1])
                losses[f"box_l1_l{l}"], losses[f"box_focal_l{l}"] = box.l1, box.focal
                total = total + self.lambda_3d * (box.l1 + box.focal)
                stats["boxes_matched"] += box.num_matched
                stats["nonfinite_match_costs"] += box.num_nonfinite_costs
                stats["nonfinite_box_targets"] += box.num_nonfinite_targets

            if rendered is not None:
                ren = rendered[l - 1]
                losses[f"render_depth_l{l}"], losses[f"render_sem_l{l}"] = ren.depth, ren.semantic
                total = total + self.render_weights[l - 1] * (ren.depth + ren.semantic)
                stats["render_pixels"] += ren.num_pixels
                stats["render_labelled_pixels"] += ren.num_labelled
        losses["loss"] = total
        return losses

    def _check_losses(self, losses: dict, targets_finite: torch.Tensor, stats: dict) -> None:
        """One host read for every term, the total and the render targets."""
        bad = nonfinite_names({**losses, NONFINITE_TARGET: torch.where(targets_finite, 0.0,
                                                                       float("nan"))})
        if NONFINITE_TARGET in bad:
            raise ValueError(NONFINITE_TARGET)
        if bad:
            raise FloatingPointError(f"non-finite loss terms: {', '.join(bad)}")
        if stats["nonfinite_match_costs"]:
            log.warning("%d NaN/inf box matching costs replaced this step",
                        stats["nonfinite_match_costs"])


# the loss term each network output enters first, for the error message
_TERM_OF_OUTPUT = {"means": "occ_chamfer", "logits": "occ_focal", "boxes": "box_l1",
                   "box_logits": "box_focal", "scales": "render_depth",
                   "rotations": "render_depth", "opacities": "render_depth"}


def network_outputs(output) -> dict[tuple[str, str], torch.Tensor]:
    """{(loss term, output name): tensor} of every network output the losses read."""
    named = {("occ_chamfer_l0", "init_means"): output.init_means}
    for l, layer in enumerate(output.layers, start=1):
        for name, term in _TERM_OF_OUTPUT.items():
            t = getattr(layer, name, None)
            if t is not None:
                named[(f"{term}_l{l}", name)] = t
    return named


def nonfinite_names(named: dict) -> list:
    """The keys of the tensors holding a NaN or inf, with one host read for all of them."""
    if not named:
        return []
    flags = torch.stack([torch.isfinite(t.detach()).all() for t in named.values()]).tolist()
    return [name for name, finite in zip(named, flags) if not finite]


def _require_finite(named: dict) -> None:
    """Non-finite network outputs (a diverging step) cannot be searched for neighbours or
    rendered: raise the criterion's FloatingPointError naming the terms (the trainer skips
    and counts the step), not the ValueError those functions keep for bad input."""
    bad = nonfinite_names(named)
    if bad:
        terms = dict.fromkeys(term for term, _ in bad)
        outputs = dict.fromkeys(name for _, name in bad)
        raise FloatingPointError(f"non-finite loss terms: {', '.join(terms)} (non-finite "
                                 f"network output {', '.join(outputs)})")
