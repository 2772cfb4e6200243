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
from ..network.budget import QueryBudget, output_needs
from ..network.padding import pad_occupancy
from ..network.postprocess import box_list, occupancy_grid


def dynamic_class_miou(result: dict, dynamic=DYNAMIC_OCC_CLASSES) -> float | None:
    """Mean IoU over the moving classes (``dynamic``: names) present in the split (paper
    Table 2's view)."""
    values = [result["per_class"][c]["IoU"] for c in dynamic
              if result["per_class"].get(c, {}).get("IoU") is not None]
    return round(float(np.mean(values)), 2) if values else None


def add_box_sample(score: DetectionScore, output, batch, cfg) -> None:
    """All of the sample's predicted boxes (no score threshold: AP ranks them) against its GT
    boxes (``add_box_list``)."""
    add_box_list(score, box_list(output, cfg, score_threshold=0.0)[0], batch["gt_boxes"][0],
                 batch["gt_labels"][0], cfg)


def add_box_list(score: DetectionScore, boxes: list[dict], gt_boxes, gt_labels, cfg) -> None:
    """Predicted boxes (``box_dicts``) whose centre lies inside the grid's x-y range, against
    the GT boxes (tensors; the dataset keeps those inside)."""
    # the GT's layout (cx, cy, cz, w, l, h, yaw, vx, vy): the TP errors need all of it
    pred = np.array([[*b["center"], *b["size"], b["yaw"], *b["velocity"]] for b in boxes],
                    dtype=np.float64).reshape(-1, 9)
    labels = np.array([b["label"] for b in boxes], dtype=np.int64)
    scores = np.array([b["score"] for b in boxes], dtype=np.float64)
    keep = inside_bev_range(pred[:, :3], cfg.pc_range)
    score.add(pred[keep], labels[keep], scores[keep], gt_boxes.cpu().numpy(),
              gt_labels.cpu().numpy())


def predicted_grid(output, cfg) -> np.ndarray:
    """The first sample's label grid uint8 [X, Y, Z], padded when cfg.occupancy_padding."""
    labels, confidence = occupancy_grid(output, cfg)
    if cfg.occupancy_padding:
        labels, _ = pad_occupancy(labels, confidence, cfg.num_classes, cfg.score_threshold)
    return labels[0].cpu().numpy()


@torch.no_grad()
def predict_split(model, dataset: OccDataset, limit: int | None = None, device="cpu",
                  workers: int = 0, progress: bool = True, desc: str = "eval",
                  budget_for=None, **decode_options):
    """Run ``model`` over the first ``limit`` samples of ``dataset``: yields (index, batch on
    ``device``, output), one sample at a time. decode_options go to ``ODG.decode``;
    budget_for(index), if given, is called right before a sample runs (after the caller has
    seen the previous output) for its query budget."""
    indices = list(range(len(dataset)))[:limit]
    loader = torch.utils.data.DataLoader(torch.utils.data.Subset(dataset, indices),
                                         batch_size=1, collate_fn=collate, num_workers=workers)
    model.eval()
    for index, batch in zip(indices, tqdm(loader, desc=desc, disable=not progress)):
        batch = to_device(batch, device)
        if budget_for is not None:
            decode_options["budget"] = budget_for(index)
        yield index, batch, model(batch["images"], batch["ego2img"], batch["ego_warp"],
                                  batch["time_delta"], **decode_options)


class BudgetUse:
    """The query budget of each keyframe of an evaluation: a fixed ``QueryBudget``, or the
    ``BudgetPolicy`` of ``query_budget: auto`` fed each keyframe's needs (reset at every new
    scene, as the node resets at a new drive), and how many queries each one refined."""

    def __init__(self, budget, infos: list[dict], cfg):
        # a policy (online/budget_policy.py, a layer up) is anything not a fixed budget
        self.policy = None if isinstance(budget, QueryBudget) else budget
        self.fixed = None if self.policy is not None else budget
        self.infos, self.cfg = infos, cfg
        self.used: list[str] = []
        self.described: dict[str, str] = {}
        self.refined: list[float] = []
        self._scene = self.current = None

    def __call__(self, index: int):
        """The budget of keyframe ``index`` (called right before it runs)."""
        self.current = self.fixed
        if self.policy is not None:
            scene = self.infos[index].get("scene_token")
            if scene != self._scene:
                self.policy.reset()
                self._scene = scene
            self.current = self.policy.budget
        return self.current

    def record(self, output, model) -> None:
        """After the keyframe ran: count its budget, feed its needs to the policy."""
        cfg, budget = self.cfg, self.current
        self.used.append(budget.name)
        self.described.setdefault(budget.name, budget.describe(cfg))
        self.refined.append(budget.refined_fraction(cfg))
        if self.policy is not None:
            self.policy.update(*output_needs(output, model, cfg))

    def result(self) -> dict:
        """mode, mean_refined_fraction, keyframes_per_budget {name: keyframes} and
        budgets {name: the budget in words (QueryBudget.describe)}."""
        counts = {name: self.used.count(name) for name in dict.fromkeys(self.used)}
        return {"mode": "auto" if self.policy is not None else self.fixed.name,
                "mean_refined_fraction": round(float(np.mean(self.refined)), 4),
                "keyframes_per_budget": counts, "budgets": dict(self.described)}


@torch.no_grad()
def evaluate(model, cfg, infos, occ_root=None, save_pred: str | None = None, device="cpu",
             rayiou: bool = True, limit: int | None = None, progress: bool = True,
             workers: int = 0, frames: int | None = None, miou_convention: str = "sparseocc",
             budget=None, **decode_options) -> dict:
    """frames: history length fed to the model (<= cfg.num_frames; the model repeats the
    oldest frame for the rest). miou_convention: see metrics/miou.py. budget: a
    ``network.budget.QueryBudget`` for every keyframe, or an ``online.budget_policy.
    BudgetPolicy`` (query_budget auto), or None (every query); the result then says which
    budgets ran (``query_budget``). decode_options go to ``ODG.decode``. The result also
    says whether the grid was padded and, with save_pred, where the predictions went
    (``predictions``: folder, files)."""
    data_cfg = cfg if frames is None else cfg.replace(num_frames=frames)
    dataset = OccDataset(infos, data_cfg, occ_root=occ_root, train=False)
    score = OccScore(dataset.dataset, rayiou=rayiou, miou_convention=miou_convention)
    boxes = DetectionScore() if cfg.dynamic_queries else None
    origins = LidarOrigins(dataset.infos) if rayiou else None
    if save_pred:
        Path(save_pred).mkdir(parents=True, exist_ok=True)
    use = BudgetUse(budget, dataset.infos, cfg) if budget is not None else None
    saved = 0
    for index, batch, output in predict_split(model, dataset, limit, device, workers, progress,
                                              budget_for=use, **decode_options):
        if use is not None:
            use.record(output, model)
        grid = predicted_grid(output, cfg)
        if save_pred:
            np.savez_compressed(Path(save_pred) / f"{batch['token'][0]}.npz", semantics=grid)
            saved += 1
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
    if use is not None:
        result["query_budget"] = use.result()
    if save_pred:
        result["predictions"] = {"folder": str(save_pred), "files": saved}
    return result
