"""The post-processing as it was with data-dependent shapes (a per-sample loop, ``unique``,
boolean indexing, a host read per box field): the reference the static-shape
post-processing (network/postprocess.py) is tested against, and a known source of host
reads for the sync counter's own check."""
import torch

from odg_ros.classes import BOX_CLASSES, FREE_LABEL
from odg_ros.network.postprocess import decode_box_code


@torch.no_grad()
def occupancy_grid(output, cfg, free_label=FREE_LABEL):
    """-> labels uint8 [B, X, Y, Z] (17 = free), confidence uint8 [B, X, Y, Z] (0..255)."""
    layer = output.last
    means, scores = layer.means.float(), layer.logits.float().sigmoid()
    B = means.shape[0]
    X, Y, Z = cfg.grid_shape
    lo = torch.tensor(cfg.pc_range[:3], device=means.device)
    centroid = means.mean(dim=2, keepdim=True)
    best = scores.max(dim=-1).values
    keep = (best > cfg.score_threshold) & (
        (means - centroid).norm(dim=-1) <= cfg.max_distance_to_centroid)
    index = torch.floor((means - lo) / cfg.voxel_size).long()
    inside = ((index >= 0) & (index < torch.tensor([X, Y, Z], device=means.device))).all(-1)
    keep &= inside & torch.isfinite(means).all(-1)
    labels = torch.full((B, X * Y * Z), free_label, dtype=torch.uint8, device=means.device)
    confidence = torch.zeros((B, X * Y * Z), dtype=torch.uint8, device=means.device)
    for b in range(B):  # per sample: the number of kept points differs
        idx = index[b][keep[b]]
        if idx.numel() == 0:
            continue
        flat = (idx[:, 0] * Y + idx[:, 1]) * Z + idx[:, 2]
        voxels, inverse = torch.unique(flat, return_inverse=True)
        summed = torch.zeros(len(voxels), scores.shape[-1], device=means.device)
        summed.index_add_(0, inverse, scores[b][keep[b]])
        counts = torch.bincount(inverse, minlength=len(voxels)).unsqueeze(1)
        mean_scores = summed / counts
        top, label = mean_scores.max(dim=1)
        labels[b, voxels] = label.to(torch.uint8)
        confidence[b, voxels] = (top * 255).round().clamp(0, 255).to(torch.uint8)
    return labels.view(B, X, Y, Z), confidence.view(B, X, Y, Z)


@torch.no_grad()
def box_list(output, cfg, score_threshold=None):
    """-> per sample a list of dicts {label, class_name, score, center, size (w, l, h), yaw,
    velocity}, sorted by score, for dynamic queries whose score passes the threshold."""
    threshold = cfg.box_score_threshold if score_threshold is None else score_threshold
    layer = output.last
    if layer.boxes is None:
        return [[] for _ in range(layer.means.shape[0])]
    probs = layer.box_logits.float().sigmoid()
    score, label = probs.max(dim=-1)
    boxes = decode_box_code(layer.boxes.float())
    # the code, not only the decoded box: the size clamp would turn an inf code into 50 m
    finite = torch.isfinite(layer.boxes.float()).all(-1) & torch.isfinite(boxes).all(-1)
    result = []
    for b in range(boxes.shape[0]):
        keep = (score[b] > threshold) & finite[b]
        order = torch.argsort(score[b][keep], descending=True)
        sel_boxes, sel_score, sel_label = boxes[b][keep][order], score[b][keep][order], \
            label[b][keep][order]
        result.append([{
            "label": int(l), "class_name": BOX_CLASSES[int(l)], "score": float(s),
            "center": bx[:3].tolist(), "size": bx[3:6].tolist(), "yaw": float(bx[6]),
            "velocity": bx[7:9].tolist()} for bx, s, l in zip(sel_boxes, sel_score, sel_label)])
    return result
