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
from ..metrics.planner import ConfidenceScore, FlipScore, VisibilityScore, bev_cells
from ..metrics.rayiou import LidarOrigins
from ..metrics.score import OccScore
from ..network.budget import QueryBudget, output_needs
from ..network.calibration import Calibration
from ..network.padding import pad_occupancy
from ..network.postprocess import box_list, occupancy_grid, stray_voxels
from ..network.visibility import DEFAULT_MIN_CLEAR, Visibility, image_bounds


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


def padded_grid(output, cfg):
    """The first sample's labels and raw confidence (score x 255), uint8 [X, Y, Z] tensors,
    padded when cfg.occupancy_padding: the grid the online step publishes."""
    labels, confidence = occupancy_grid(output, cfg)
    if cfg.occupancy_padding:
        labels, confidence = pad_occupancy(labels, confidence, cfg.num_classes,
                                           cfg.score_threshold)
    return labels[0], confidence[0]


def predicted_grid(output, cfg) -> np.ndarray:
    """The first sample's label grid uint8 [X, Y, Z], padded when cfg.occupancy_padding."""
    return padded_grid(output, cfg)[0].cpu().numpy()


class PublishedGrid:
    """What the online step publishes for a model output (step.OnlineStep): the padded labels,
    the confidence (calibrated where the checkpoint has a calibration) and the voxels the
    cameras observe; and the observed voxels of the ground-truth grid (the method's ceiling:
    the predicted surfaces alone, no hazard)."""

    def __init__(self, cfg, device="cpu", min_clear: float = DEFAULT_MIN_CLEAR):
        self.cfg = cfg
        self.calibration = Calibration(cfg, device)
        grid = (cfg.grid_shape, cfg.pc_range, cfg.voxel_size, cfg.num_classes)
        self.visibility = Visibility(*grid, min_clear, device=device)
        self.truth_visibility = Visibility(*grid, 0.0, device=device)

    @staticmethod
    def geometry(ego2img, image_hws, input_hw, device):
        """The current set's ego2img [N, 4, 4] (array) -> (ego2img, img2ego, bounds) tensors
        on ``device`` as the node packs them."""
        ego2img = np.asarray(ego2img, np.float64)
        return (torch.tensor(ego2img, dtype=torch.float32, device=device),
                torch.tensor(np.linalg.inv(ego2img), dtype=torch.float32, device=device),
                torch.tensor(image_bounds(image_hws, input_hw), device=device))

    def __call__(self, output, geometry) -> dict:
        """-> {"grid", "raw", "confidence", "observed"} numpy [X, Y, Z] (uint8, bool)."""
        labels, raw = (t.reshape(-1) for t in padded_grid(output, self.cfg))
        confidence, hazard = self.calibration(labels, raw)
        stray = stray_voxels(output.last.means[:1], output.last.logits[:1], self.cfg)[0]
        observed = self.visibility(labels, *geometry, hazard=hazard, stray=stray)
        shape = self.cfg.grid_shape
        return {"grid": labels.view(shape).cpu().numpy(), "raw": raw.view(shape).cpu().numpy(),
                "confidence": confidence.view(shape).cpu().numpy(),
                "observed": observed.view(shape).cpu().numpy().astype(bool)}

    def truth_observed(self, truth: np.ndarray, geometry) -> np.ndarray:
        labels = torch.as_tensor(np.ascontiguousarray(truth).reshape(-1),
                                 device=geometry[0].device)
        return self.truth_visibility(labels, *geometry).view(self.cfg.grid_shape) \
            .cpu().numpy().astype(bool)

    def boxes(self, output) -> list[dict]:
        """The boxes of one output as the node publishes them: calibrated scores."""
        boxes = box_list(output, self.cfg)[0]
        scores = self.calibration.box_score(
            torch.tensor([b["score"] for b in boxes], dtype=torch.float32))
        for box, calibrated in zip(boxes, scores.tolist()):
            box["score"] = calibrated
        return boxes


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


# the node's default BEV height band (bev_min_z, bev_max_z), metres in the grid frame
BEV_BAND = (-1.0, 2.0)


class SetScore:
    """Everything ``evaluate`` scores over a set of keyframes."""

    def __init__(self, dataset: str, cfg, rayiou: bool, miou_convention: str):
        labels = occ_labels(dataset)
        self.dataset = dataset
        self.occ = OccScore(dataset, rayiou=rayiou, miou_convention=miou_convention)
        self.boxes = DetectionScore() if cfg.dynamic_queries else None
        self.visibility, self.truth_visibility = VisibilityScore(), VisibilityScore()
        self.confidence = ConfidenceScore(labels.names[:-1])
        self.flips = FlipScore(labels)

    def result(self, cfg, min_clear: float, calibrated: bool) -> dict:
        result = self.occ.result()
        result["mIoU_dynamic"] = dynamic_class_miou(result, occ_labels(self.dataset).dynamic)
        result["occupancy_padding"] = bool(cfg.occupancy_padding)
        if self.boxes is not None:
            result["boxes"] = self.boxes.result()
        result["visibility"] = {"min_clear": min_clear, "model": self.visibility.result(),
                                "ground_truth_grid": self.truth_visibility.result()}
        result["confidence"] = {"calibrated": calibrated, **self.confidence.result()}
        result["stability"] = self.flips.result()
        return result


def add_planner_scores(scores, cfg, publish, published: dict, geometry, now: dict,
                       before: dict | None, boxes: list, batch, bev_band) -> None:
    """What a planner reads of one keyframe (``now``: its grid, truth, mask, pose and scene;
    ``before``: the previous keyframe's) into each SetScore of ``scores``."""
    grid, truth, mask = now["grid"], now["truth"], now["mask"]
    truth_observed = publish.truth_observed(truth, geometry)
    band = (cfg.pc_range, cfg.voxel_size, bev_band, cfg.labels)
    truth_bev = bev_cells(truth, mask, *band)
    for s in scores:
        s.visibility.add(grid, published["observed"], truth, mask, cfg.num_classes,
                         bev_cells(grid, published["observed"], *band), truth_bev)
        s.truth_visibility.add(truth, truth_observed, truth, mask, cfg.num_classes,
                               bev_cells(truth, truth_observed, *band), truth_bev)
        s.confidence.add(grid, published["confidence"], truth, mask, cfg.num_classes)
        s.confidence.add_boxes(boxes, batch["gt_boxes"][0].cpu().numpy(),
                               batch["gt_labels"][0].cpu().numpy())
        if before is not None and before["scene"] == now["scene"]:
            s.flips.add(before, now, cfg.grid_shape, cfg.pc_range, cfg.voxel_size)


@torch.no_grad()
def evaluate(model, cfg, infos, occ_root=None, save_pred: str | None = None, device="cpu",
             rayiou: bool = True, limit: int | None = None, progress: bool = True,
             workers: int = 0, frames: int | None = None, miou_convention: str = "sparseocc",
             budget=None, min_clear: float = DEFAULT_MIN_CLEAR, bev_band=BEV_BAND,
             **decode_options) -> dict:
    """infos: one split (a path or the loaded dict), or {name: split} of several (scene
    classes), scored each (``sets``) and together. limit: the first N keyframes of each.
    frames: history length (<= cfg.num_frames; the oldest frame repeats for the rest).
    miou_convention: metrics/miou.py. budget: a ``QueryBudget``, a ``BudgetPolicy``
    (query_budget auto) or None (every query); ``query_budget`` then says which ran.
    decode_options go to ``ODG.decode``. Also: whether the grid was padded, where
    save_pred wrote (``predictions``), and what a planner reads of the grid as the node
    publishes it (``PublishedGrid``, metrics/planner.py): ``visibility`` against
    mask_camera (voxels, the BEV of height ``bev_band``, the ground-truth grid's beside
    them as the ceiling), ``confidence`` (calibration error) and ``stability`` (label flips
    between consecutive keyframes at voxels static in the ground truth)."""
    named = isinstance(infos, dict) and "infos" not in infos
    sets = dict(infos) if named else {None: infos}
    data_cfg = cfg if frames is None else cfg.replace(num_frames=frames)
    publish = PublishedGrid(cfg, device, min_clear)
    if save_pred:
        Path(save_pred).mkdir(parents=True, exist_ok=True)
    use, overall, per_set, saved = None, None, {}, 0
    for name, split in sets.items():
        dataset = OccDataset(split, data_cfg, occ_root=occ_root, train=False)
        score = SetScore(dataset.dataset, cfg, rayiou, miou_convention)
        if overall is None:
            overall = SetScore(dataset.dataset, cfg, rayiou, miou_convention)
        scores = [score, overall]
        origins = LidarOrigins(dataset.infos) if rayiou else None
        if budget is not None:
            use = use or BudgetUse(budget, dataset.infos, cfg)
            use.infos = dataset.infos
        before = None
        description = "eval" if name is None else f"eval {name}"
        for index, batch, output in predict_split(model, dataset, limit, device, workers,
                                                  progress, desc=description, budget_for=use,
                                                  **decode_options):
            if use is not None:
                use.record(output, model)
            info = dataset.infos[index]
            geometry = publish.geometry(
                batch["ego2img"][0, 0].cpu().numpy(),
                [info["cams"][c]["image_hw"] for c in dataset.camera_names], cfg.image_size,
                device)
            published = publish(output, geometry)
            grid = published["grid"]
            if save_pred:
                np.savez_compressed(Path(save_pred) / f"{batch['token'][0]}.npz",
                                    semantics=grid)
                saved += 1
            boxes = publish.boxes(output)
            for s in scores:
                if s.boxes is not None:
                    add_box_sample(s.boxes, output, batch, cfg)
            if not batch["has_occ"][0]:
                before = None
                continue
            truth = batch["occ_semantics"][0].cpu().numpy()
            mask = batch["occ_mask_camera"][0].cpu().numpy().astype(bool)
            score.occ.add(grid, truth, mask, origins(index) if origins is not None else None)
            now = {"scene": info["scene_token"], "grid": grid, "truth": truth, "mask": mask,
                   "pose": np.asarray(info["ego_pose"], np.float64)}
            add_planner_scores(scores, cfg, publish, published, geometry, now, before, boxes,
                               batch, bev_band)
            before = now
        overall.occ.merge(score.occ)
        per_set[name] = score
    calibrated = publish.calibration.calibrated
    result = overall.result(cfg, min_clear, calibrated)
    if named:
        result["sets"] = {name: s.result(cfg, min_clear, calibrated)
                          for name, s in per_set.items()}
    return _with_budget_and_predictions(result, use, save_pred, saved)


def _with_budget_and_predictions(result: dict, use, save_pred: str | None, saved: int) -> dict:
    """``result`` with which budgets ran (``query_budget``) and where the predictions went."""
    if use is not None:
        result["query_budget"] = use.result()
    if save_pred:
        result["predictions"] = {"folder": str(save_pred), "files": saved}
    return result
