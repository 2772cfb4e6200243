"""Run a model over a split and score it (mIoU with the camera mask, RayIoU, per class; the
dynamic queries' boxes by nuScenes-style mAP)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..classes import DYNAMIC_OCC_CLASSES, occ_labels
from ..data.batch import collate, to_device
from ..data.dataset import OccDataset
from ..geometry import inside_bev_range
from ..metrics.detection import DetectionScore
from ..metrics.rayiou import LidarOrigins
from ..metrics.score import OccScore
from ..network.padding import pad_occupancy
from ..network.postprocess import box_list, occupancy_grid


def dynamic_class_miou(result: dict, dynamic=DYNAMIC_OCC_CLASSES) -> float | None:
    """Mean IoU over the moving classes (``dynamic``: names) present in the split (paper
    Table 2's view)."""
    values = [result["per_class"][c]["IoU"] for c in dynamic
              if result["per_class"].get(c, {}).get("IoU") is not None]
    return round(float(np.mean(values)), 2) if values else None


def add_box_sample(score: DetectionScore, output, batch, cfg) -> None:
    """All of the sample's predicted boxes (no score threshold: AP ranks them) whose centre
    lies inside the grid's x-y range, against its GT boxes (the dataset keeps those inside)."""
    boxes = box_list(output, cfg, score_threshold=0.0)[0]
    # the GT's layout (cx, cy, cz, w, l, h, yaw, vx, vy): the TP errors need all of it
    pred = np.array([[*b["center"], *b["size"], b["yaw"], *b["velocity"]] for b in boxes],
                    dtype=np.float64).reshape(-1, 9)
    labels = np.array([b["label"] for b in boxes], dtype=np.int64)
    scores = np.array([b["score"] for b in boxes], dtype=np.float64)
    keep = inside_bev_range(pred[:, :3], cfg.pc_range)
    score.add(pred[keep], labels[keep], scores[keep], batch["gt_boxes"][0].cpu().numpy(),
              batch["gt_labels"][0].cpu().numpy())


def predicted_grid(output, cfg) -> np.ndarray:
    """The first sample's label grid uint8 [X, Y, Z], padded when cfg.occupancy_padding."""
    labels, confidence = occupancy_grid(output, cfg)
    if cfg.occupancy_padding:
        labels, _ = pad_occupancy(labels, confidence, cfg.num_classes, cfg.score_threshold)
    return labels[0].cpu().numpy()


@torch.no_grad()
def predict_split(model, dataset: OccDataset, limit: int | None = None, device="cpu",
                  workers: int = 0, progress: bool = True, desc: str = "eval",
                  **decode_options):
    """Run ``model`` over the first ``limit`` samples of ``dataset``: yields (index, batch on
    ``device``, output), one sample at a time. decode_options go to ``ODG.decode``."""
    indices = list(range(len(dataset)))[:limit]
    loader = torch.utils.data.DataLoader(torch.utils.data.Subset(dataset, indices),
                                         batch_size=1, collate_fn=collate, num_workers=workers)
    model.eval()
    for index, batch in zip(indices, tqdm(loader, desc=desc, disable=not progress)):
        batch = to_device(batch, device)
        yield index, batch, model(batch["images"], batch["ego2img"], batch["ego_warp"],
                                  batch["time_delta"], **decode_options)


@torch.no_grad()
def evaluate(model, cfg, infos, occ_root=None, save_pred: str | None = None, device="cpu",
             rayiou: bool = True, limit: int | None = None, progress: bool = True,
             workers: int = 0, frames: int | None = None, miou_convention: str = "sparseocc",
             **decode_options) -> dict:
    """frames: history length fed to the model (<= cfg.num_frames; the model repeats the
    oldest frame for the rest). miou_convention: see metrics/miou.py. decode_options go to
    ``ODG.decode`` (e.g. prune=...). The result also says whether the grid was padded."""
    data_cfg = cfg if frames is None else cfg.replace(num_frames=frames)
    dataset = OccDataset(infos, data_cfg, occ_root=occ_root, train=False)
    score = OccScore(dataset.dataset, rayiou=rayiou, miou_convention=miou_convention)
    boxes = DetectionScore() if cfg.dynamic_queries else None
    origins = LidarOrigins(dataset.infos) if rayiou else None
    if save_pred:
        Path(save_pred).mkdir(parents=True, exist_ok=True)
    for index, batch, output in predict_split(model, dataset, limit, device, workers, progress,
                                              **decode_options):
        grid = predicted_grid(output, cfg)
        if save_pred:
            np.savez_compressed(Path(save_pred) / f"{batch['token'][0]}.npz", semantics=grid)
        if boxes is not None:
            add_box_sample(boxes, output, batch, cfg)
        if not batch["has_occ"][0]:
            continue
        score.add(grid, batch["occ_semantics"][0].cpu().numpy(),
                  batch["occ_mask_camera"][0].cpu().numpy().astype(bool),
                  origins(index) if origins is not None else None)
    result = score.result()
    result["mIoU_dynamic"] = dynamic_class_miou(result, occ_labels(dataset.dataset).dynamic)
    result["occupancy_padding"] = bool(cfg.occupancy_padding)
    if boxes is not None:
        result["boxes"] = boxes.result()
    return result
