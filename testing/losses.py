"""The loss tests' tiny network output and training batch (two cameras facing front and back),
and a float64 reference of the occupancy loss."""
from __future__ import annotations

import math

import torch

from odg_ros.classes import OCC_CLASS_WEIGHTS
from odg_ros.model_config import ModelConfig
from odg_ros.losses.focal import sigmoid_focal_loss
from odg_ros.network.outputs import LayerOutput, ODGOutput

B, N, H, W = 2, 2, 32, 64
CFG = ModelConfig(name="tiny", num_static=6, num_dynamic=2, points_per_layer=(1, 2, 2, 2, 2, 3),
                  image_size=(H, W), num_cams=N)
K = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 16.0], [0, 0, 1]])
FRONT = torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]])
BACK = torch.tensor([[0.0, 1, 0, 0], [0, 0, -1, 0], [-1, 0, 0, 0], [0, 0, 0, 1]])


def make_output(cfg=CFG, boxes=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    Q, D = cfg.num_queries, cfg.num_dynamic
    layers = []
    for k in cfg.points_per_layer:
        means = torch.randn(B, Q, k, 3, generator=g) * torch.tensor([8.0, 8.0, 1.0])
        rot = torch.randn(B, Q, k, 4, generator=g)
        layers.append(LayerOutput(
            means=means.requires_grad_(True),
            logits=torch.randn(B, Q, k, cfg.num_classes, generator=g, requires_grad=True),
            scales=(torch.rand(B, Q, k, 3, generator=g) + 0.3).requires_grad_(True),
            rotations=(rot / rot.norm(dim=-1, keepdim=True)).requires_grad_(True),
            opacities=torch.rand(B, Q, k, generator=g).clamp(0.05, 0.95).requires_grad_(True),
            boxes=torch.randn(B, D, 10, generator=g, requires_grad=True) if boxes else None,
            box_logits=torch.randn(B, D, 10, generator=g, requires_grad=True) if boxes else None))
    init = (torch.randn(B, Q, 1, 3, generator=g) * 8).requires_grad_(True)
    return ODGOutput(init_means=init, layers=layers, num_dynamic=D)


def make_batch(occupied=True, boxes=True, lidar=True):
    sem = torch.full((B, 200, 200, 16), 17, dtype=torch.uint8)
    if occupied:
        sem[0, 110:120, 95:105, 2:4] = 4            # a car ahead (x 4..8 m)
        sem[0, 100:140, 80:120, 0] = 11              # road ahead
        sem[1, 80:90, 100:102, 3] = 8                # traffic cones behind
    mask = torch.zeros_like(sem, dtype=torch.bool)
    mask[:, 90:, :, :] = True
    gt_boxes = [torch.tensor([[6.0, 0.0, 0.0, 2.0, 4.0, 1.6, 0.1, 1.0, 0.0]]),
                torch.tensor([[-6.0, 0.4, 0.4, 0.4, 0.4, 0.8, 0.0, float("nan"), float("nan")],
                              [-7.0, 0.4, 0.4, 0.4, 0.4, 0.8, 0.0, 0.0, 0.0]])]
    gt_labels = [torch.tensor([0]), torch.tensor([9, 9])]
    if not boxes:
        gt_boxes = [torch.zeros(0, 9)] * B
        gt_labels = [torch.zeros(0, dtype=torch.long)] * B
    g = torch.Generator().manual_seed(5)

    def lidar_points(n):
        if not lidar:
            return torch.zeros(0, 4)
        uv = torch.rand(n, 2, generator=g) * torch.tensor([W - 1.0, H - 1.0]) + 0.5
        return torch.cat([uv, torch.rand(n, 1, generator=g) * 20 + 2,
                          torch.randint(0, 18, (n, 1), generator=g).float()], 1)

    return {
        "occ_semantics": sem, "occ_mask_camera": mask, "occ_mask_lidar": mask.clone(),
        "gt_boxes": gt_boxes, "gt_labels": gt_labels,
        "render_targets": [[lidar_points(40), lidar_points(7)] for _ in range(B)],
        "cam_from_ego": torch.stack([FRONT, BACK]).expand(B, N, 4, 4).clone(),
        "intrinsics": K.expand(B, N, 3, 3).clone(),
    }


def all_output_tensors(out):
    tensors = [out.init_means]
    for layer in out.layers:
        tensors += [layer.means, layer.logits, layer.scales, layer.rotations, layer.opacities]
        if layer.boxes is not None:
            tensors += [layer.boxes, layer.box_logits]
    return tensors


def reference_occupancy(points, logits, centres, labels, visible, pc_range):
    """Direct transcription of the OPUS rules with a full distance matrix, float64."""
    p, g = points.double(), centres.double()
    d = torch.cdist(p, g)
    p2g, g2p = d.argmin(1), d.argmin(0)
    pred_term = torch.nn.functional.smooth_l1_loss(p, g[p2g], beta=0.2, reduction="sum") / len(p)
    gd = (g - p[g2p]).norm(dim=-1)
    w = torch.ones(len(g), dtype=torch.float64)
    w[(gd > 0.2) & visible] = 5
    rare = torch.isin(labels, torch.tensor([0, 2, 5, 8])) & visible
    w[rare] = torch.clamp(w[rare], min=10)
    gt_term = (w[:, None] * torch.nn.functional.smooth_l1_loss(
        g, p[g2p], beta=0.2, reduction="none")).sum() / len(g)
    chamfer = 0.5 * (pred_term + gt_term)
    t = torch.zeros(len(p), 17, dtype=torch.float64)
    t[torch.arange(len(p)), labels[p2g]] = 1
    cx, cy = (pc_range[0] + pc_range[3]) / 2, (pc_range[1] + pc_range[4]) / 2
    dw = 1 + torch.hypot(g[p2g, 0] - cx, g[p2g, 1] - cy) / math.hypot(
        pc_range[3] - pc_range[0], pc_range[4] - pc_range[1])
    cw = torch.tensor(OCC_CLASS_WEIGHTS, dtype=torch.float64)
    focal = 2.0 * (cw * dw[:, None] * sigmoid_focal_loss(logits.double(), t)).sum() / len(p)
    return chamfer, focal
