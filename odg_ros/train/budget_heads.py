"""Training the query-budget heads (network/budget.py) of a trained model, the rest frozen.

1. ``collect``: the model at full budget over a split; per keyframe, the decoder's inputs
   (sampling layout of the frames' features, geometry), every query's state after
   AFTER_LAYER (feature, means, boxes, best point / box logits), the last layer's points,
   logits and boxes (the teacher) and the camera mask, one file per keyframe (the
   features are most of it: ~25 MB a keyframe for odg_cpu, in float16).
2. ``fit_skip_layer``: the skip layer learns the last layer's output of every query from
   its state after AFTER_LAYER (distillation, point by point and box by box; it starts as
   layer AFTER_LAYER + 1 with the last layer's point and box heads).
3. ``refinement_change``: per query, how much the later layers change its part of the grid
   against the skip layer's output: the (voxel, class) pairs one output has and the other
   not, in the camera mask, each weighted by what a voxel of its class is worth to this
   keyframe's mIoU (the inverse of the class's voxels in the full output's grid). No ground
   truth: the model's own full output is the reference, so the heads can learn on any drive.
4. ``fit_keep_scores``: the keep-score heads regress that change, so that a budget refines
   the queries whose output the later layers change most.
5. ``calibrate_skip_layer``: the skip layer's class logits are lowered by the offset under
   which the budgets' grids agree best with the full model's (voxels and rays, no ground
   truth). Distilled without image sampling, the skip layer is surer than the last layer
   where it should not be: its extra points are floaters that cut rays short (RayIoU).
Everything after ``collect`` runs on the cached keyframes. ``train_budget_heads`` runs the
five steps and writes the checkpoint with the heads (``odg train --budget-heads``).

A ground-truth gain (correct voxels won by refining) ranks worse than this change: it is
noisy per query, and with weights fixed per class over a training set it spends a budget on
classes that fill an open road's view (terrain) and loses the small ones (docs/query_budget.md).
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..data.dataset import OccDataset
from ..metrics.miou import MIoU
from ..metrics.rayiou import RayIoU
from ..network.budget import (AFTER_LAYER, QueryBudget, best_logits, budget_ladder,
                              gather_queries, keep_inputs, ranked_queries)
from ..network.checkpoint import load_model, read_checkpoint, save_checkpoint
from ..network.decoder import merged_layer
from ..network.outputs import LayerOutput
from ..network.postprocess import point_voxels, voxelise

# keyframe_class_weights: a voxel is worth SCALE / (its class's voxels + FLOOR), so that a
# class of a few voxels does not outweigh every other one
CLASS_WEIGHT_SCALE = 1000.0
CLASS_WEIGHT_FLOOR = 100.0
# a query whose refinement is predicted to change the grid by more than this counts as
# needed by ``query_budget: auto`` (chosen on held-out scenes of each class,
# docs/results/query_budget.md)
NEED_CHANGE = 24.0
# calibrate_skip_layer: the offsets tried, and where its rays start (a roof LiDAR's height
# over the ego origin: the full grid's first hits are the reference, not a sensor's)
SKIP_OFFSETS = tuple(0.25 * i for i in range(13))
RAY_ORIGIN = (0.0, 0.0, 1.8)


@dataclass
class QueryState:
    """What the keep-scores see of one keyframe (kept in memory): Q queries, dynamic first."""
    query: torch.Tensor          # [Q, E] feature after AFTER_LAYER
    inputs: torch.Tensor         # [Q, KEEP_INPUTS] (network.budget.keep_inputs)


class DecoderCapture:
    """Hooks on the decoder (its inputs) and on layer AFTER_LAYER (its outputs)."""

    def __init__(self, decoder):
        self.inputs = self.after = None
        self.handles = [decoder.register_forward_pre_hook(self._inputs),
                        decoder.layers[AFTER_LAYER - 1].register_forward_hook(self._after)]

    def _inputs(self, module, args):
        self.inputs = args

    def _after(self, module, args, output):
        self.after = output

    def remove(self):
        for handle in self.handles:
            handle.remove()


def _half(t):
    return t.half() if t is not None and t.is_floating_point() else t


@torch.no_grad()
def collect(model, dataset, indices, cache_dir, progress: bool = True,
            desc: str = "collect") -> list[Path]:
    """Run ``model`` (eval, full budget) over ``dataset[indices]``; one file per keyframe in
    ``cache_dir`` (kept if it exists: a stopped pass resumes) -> the files."""
    from ..data.batch import collate, to_device
    model.eval()
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for index in tqdm(indices, desc=desc, disable=not progress):
        path = cache_dir / f"{desc}-{index:05d}.pt"
        files.append(path)
        if not path.is_file():
            batch = to_device(collate([dataset[index]]), "cpu")
            inputs = (batch["images"], batch["ego2img"], batch["ego_warp"], batch["time_delta"])
            torch.save(keyframe_record(model, inputs, batch["occ_mask_camera"][0]), path)
    return files


@torch.no_grad()
def keyframe_record(model, inputs, mask) -> dict:
    """One keyframe (``inputs``: the model's positional inputs, batch of one; its camera
    ``mask`` [X, Y, Z]) -> what the later stages need: the decoder's inputs, every query's
    state after AFTER_LAYER, the last layer's output (the teacher; its means in float32, as
    voxel boundaries need them) and the mask."""
    capture = DecoderCapture(model.decoder)
    try:
        output = model(*inputs)
    finally:
        capture.remove()
    _, _, _, levels, geometry = capture.inputs[:5]
    query, means, logits, boxes, box_logits = capture.after
    point, box = best_logits(logits, box_logits, model.num_dynamic)
    last = output.last
    return {"levels": [_half(level) for level in levels],
            "geometry": {k: v for k, v in geometry.items()},
            "query": query[0], "means": means[0],
            "boxes": None if boxes is None else boxes[0],
            "point_logit": point[0], "box_logit": box[0],
            "teacher": {"means": last.means[0], "logits": _half(last.logits[0]),
                        "boxes": None if last.boxes is None else last.boxes[0],
                        "box_logits": None if last.box_logits is None
                        else last.box_logits[0]},
            "mask": mask}


def load_keyframe(path) -> dict:
    record = torch.load(path, weights_only=False)
    record["levels"] = [level.float() for level in record["levels"]]
    return record


def init_skip_layer(model) -> None:
    """The skip layer starts as layer AFTER_LAYER + 1 (whose input it takes) with the last
    layer's point and box heads (whose output it gives)."""
    layers, skip = model.decoder.layers, model.decoder.budget_heads.skip_layer
    skip.load_state_dict({k: v for k, v in layers[AFTER_LAYER].state_dict().items()
                          if not k.startswith("points.")}, strict=False)
    skip.points.load_state_dict(layers[-1].points.state_dict())
    if skip.boxes is not None:
        skip.boxes.load_state_dict(layers[-1].boxes.state_dict())


def skip_layer_output(model, record: dict, queries: torch.Tensor | None = None):
    """The skip layer over the cached keyframe's queries (``queries`` [Q''] indices, dynamic
    first; default all) -> (means, logits, boxes, box_logits) without the batch axis."""
    decoder, cfg = model.decoder, model.cfg
    D = model.num_dynamic
    query, means, boxes = record["query"], record["means"], record["boxes"]
    if queries is not None:
        query, means = query[queries], means[queries]
        D = int((queries < model.num_dynamic).sum())
        boxes = None if boxes is None else boxes[queries[:D]]
    geometry = record["geometry"]
    _, means, logits, boxes, box_logits = decoder.budget_heads.skip_layer(
        query[None], means[None], None if boxes is None else boxes[None], D, geometry,
        record["levels"], velocity_warp=cfg.motion_compensation,
        ego_warp=cfg.ego_compensation)
    return (means[0], logits[0], None if boxes is None else boxes[0],
            None if box_logits is None else box_logits[0])


def distillation_loss(output, teacher: dict, queries: torch.Tensor | None = None
                      ) -> torch.Tensor:
    """Point by point: the teacher's means (smooth L1, weighted by the teacher's score, so
    the points that reach the grid count most) and class probabilities (soft BCE); box by
    box: the box code (L1) and the box class probabilities (soft BCE)."""
    means, logits, boxes, box_logits = output
    t_means, t_logits = teacher["means"].float(), teacher["logits"].float()
    t_boxes, t_box_logits = teacher["boxes"], teacher["box_logits"]
    if queries is not None:
        t_means, t_logits = t_means[queries], t_logits[queries]
        if t_boxes is not None:
            dynamic = queries[queries < len(t_boxes)]
            t_boxes, t_box_logits = t_boxes[dynamic], t_box_logits[dynamic]
    target = t_logits.sigmoid()
    weight = target.amax(dim=-1) + 0.05                                   # [Q, K]
    position = (F.smooth_l1_loss(means, t_means, reduction="none", beta=0.4).sum(-1)
                * weight).sum() / weight.sum()
    loss = position + 10.0 * F.binary_cross_entropy_with_logits(logits, target)
    if boxes is not None and len(boxes):
        loss = loss + 0.25 * F.l1_loss(boxes, t_boxes) + \
            2.0 * F.binary_cross_entropy_with_logits(box_logits, t_box_logits.sigmoid())
    return loss


def _train_step(optimizer, schedule, loss: torch.Tensor) -> float:
    """One optimiser and schedule step on ``loss`` -> its value."""
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    schedule.step()
    return float(loss.detach())

def fit_skip_layer(model, files: list[Path], epochs: int = 20, lr: float = 1e-3,
                   seed: int = 0, progress: bool = True, log=None) -> list[float]:
    """Distil the last layer's output into the skip layer over the cached keyframes (one
    keyframe a step, every query) -> mean loss per epoch."""
    skip = model.decoder.budget_heads.skip_layer
    skip.eval().requires_grad_(True)          # no dropout: it distils a deterministic map
    optimizer = torch.optim.AdamW(skip.parameters(), lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, lr,
                                                   total_steps=epochs * len(files))
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for epoch in range(epochs):
        total = []
        order = torch.randperm(len(files), generator=generator).tolist()
        for i in tqdm(order, desc=f"skip layer {epoch + 1}/{epochs}", disable=not progress):
            record = load_keyframe(files[i])
            loss = distillation_loss(skip_layer_output(model, record), record["teacher"])
            total.append(_train_step(optimizer, schedule, loss))
        losses.append(float(np.mean(total)))
        if log is not None:
            log(f"skip layer epoch {epoch + 1}/{epochs}: loss {losses[-1]:.4f}")
    skip.eval().requires_grad_(False)
    return losses


def grid_pairs(means, logits, mask, cfg) -> torch.Tensor:
    """The distinct (query, voxel, class) triples a layer output [Q, K, 3] / [Q, K, C] puts
    into the grid (the points ``postprocess.point_voxels`` keeps), inside ``mask`` [X, Y, Z]:
    one int64 code ((query * cells + voxel) * C + class) each."""
    means, scores = means.float(), logits.float().sigmoid()
    Q, K, C = scores.shape
    keep, voxel = point_voxels(means, scores, cfg)
    keep &= mask.bool().reshape(-1)[torch.where(keep, voxel, torch.zeros_like(voxel))]
    label = scores.argmax(dim=-1)
    query = torch.arange(Q).unsqueeze(1).expand(Q, K)
    return torch.unique((query[keep] * mask.numel() + voxel[keep]) * C + label[keep])


def keyframe_class_weights(means, logits, mask, cfg) -> torch.Tensor:
    """[C] what one voxel of each class is worth to this keyframe's mIoU, from the full
    output (no ground truth): ``CLASS_WEIGHT_SCALE / (voxels of the class in its grid inside
    ``mask`` + CLASS_WEIGHT_FLOOR)``. A voxel of a class with few voxels moves that class's
    IoU much, one of a class that fills the view (terrain on an open road) hardly at all."""
    labels, _ = voxelise(means[None].float(), logits[None].float(), cfg, cfg.num_classes)
    labels = labels[0][mask.bool().reshape(-1)].long()
    counts = torch.bincount(labels, minlength=cfg.num_classes + 1)[:cfg.num_classes]
    return CLASS_WEIGHT_SCALE / (counts.float() + CLASS_WEIGHT_FLOOR)


def output_change(full, skipped, mask, weights, cfg) -> torch.Tensor:
    """[Q] per query: the class-weighted (voxel, class) pairs that one of two outputs of the
    same queries puts into the grid and the other does not (``full``, ``skipped``: (means
    [Q, K, 3], logits [Q, K, C]) each; ``weights`` [C])."""
    C = full[1].shape[-1]
    cells = math.prod(cfg.grid_shape)
    codes, counts = torch.unique(torch.cat([grid_pairs(*full, mask, cfg),
                                            grid_pairs(*skipped, mask, cfg)]),
                                 return_counts=True)
    differ = codes[counts == 1]
    label, query = differ % C, differ // (C * cells)
    return torch.zeros(len(full[0])).index_add_(0, query, weights[label])


def ground_truth_gain(full, skipped, semantics, mask, cfg) -> torch.Tensor:
    """[Q] per query: the correct (voxel, class) pairs it puts into the grid in ``full`` less
    those in ``skipped`` (outputs as in ``output_change``), each weighted by
    CLASS_WEIGHT_SCALE / (voxels of its class in ``semantics`` [X, Y, Z] inside ``mask`` +
    CLASS_WEIGHT_FLOOR). Not a training target (noisy per query, see the module's text): the
    ranking an oracle that knows the ground truth would choose, a bound for the keep-scores."""
    C, cells = full[1].shape[-1], mask.numel()
    labels = semantics.reshape(-1).long()
    counts = torch.bincount(labels[mask.bool().reshape(-1)], minlength=C + 1)[:C]
    weights = CLASS_WEIGHT_SCALE / (counts.float() + CLASS_WEIGHT_FLOOR)
    gain = torch.zeros(len(full[0]))
    for sign, output in ((1.0, full), (-1.0, skipped)):
        codes = grid_pairs(*output, mask, cfg)
        label, voxel, query = codes % C, (codes // C) % cells, codes // (C * cells)
        right = labels[voxel] == label
        gain.index_add_(0, query[right], sign * weights[label[right]])
    return gain


@torch.no_grad()
def refinement_change(model, files: list[Path], progress: bool = True):
    """Per keyframe: ([Q] how much the later layers change each query's part of the grid
    against the skip layer (``output_change`` weighted by ``keyframe_class_weights``: no
    ground truth), its QueryState)."""
    cfg = model.cfg
    changes, states = [], []
    for path in tqdm(files, desc="changes", disable=not progress):
        record = load_keyframe(path)
        means, logits, _, _ = skip_layer_output(model, record)
        teacher = (record["teacher"]["means"].float(), record["teacher"]["logits"].float())
        weights = keyframe_class_weights(*teacher, record["mask"], cfg)
        changes.append(output_change(teacher, (means, logits), record["mask"], weights, cfg))
        inputs = keep_inputs(record["means"][None], record["point_logit"][None],
                             record["box_logit"][None], cfg.pc_range)[0]
        states.append(QueryState(record["query"], inputs))
    return changes, states


def squashed(change: torch.Tensor) -> torch.Tensor:
    """The regression target: log(1 + c) of a change c >= 0, so a few huge changes do not
    dominate."""
    return change.log1p()


def fit_keep_scores(model, states: list[QueryState], changes: list[torch.Tensor],
                    epochs: int = 40, lr: float = 2e-3, keyframes_per_step: int = 8,
                    seed: int = 0, progress: bool = True, log=None) -> list[float]:
    """The static and dynamic keep-score heads regress the squashed change of their
    queries (``refinement_change``)."""
    heads = model.decoder.budget_heads
    D = model.num_dynamic
    modules = [heads.static_score] + ([heads.dynamic_score] if D else [])
    params = [p for m in modules for p in m.parameters()]
    for m in modules:
        m.train().requires_grad_(True)
    optimizer = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    steps = epochs * math.ceil(len(states) / keyframes_per_step)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, lr, total_steps=steps)
    generator = torch.Generator().manual_seed(seed)
    losses = []
    for epoch in tqdm(range(epochs), desc="keep-scores", disable=not progress):
        total = []
        order = torch.randperm(len(states), generator=generator).tolist()
        for start in range(0, len(order), keyframes_per_step):
            group = order[start:start + keyframes_per_step]
            query = torch.stack([states[i].query for i in group])
            inputs = torch.stack([states[i].inputs for i in group])
            target = squashed(torch.stack([changes[i] for i in group]))
            loss = F.mse_loss(heads.scores_of(query, inputs, D), target)
            total.append(_train_step(optimizer, schedule, loss))
        losses.append(float(np.mean(total)))
        if log is not None:
            log(f"keep-scores epoch {epoch + 1}/{epochs}: loss {losses[-1]:.4f}")
    for m in modules:
        m.eval().requires_grad_(False)
    return losses


@torch.no_grad()
def budget_last_layers(model, record: dict, budget: QueryBudget, offsets) -> dict:
    """The last layer's output of a cached keyframe under ``budget``, as the decoder's budget
    path gives it, once per skip-layer logit offset (the later layers run once) -> {offset:
    (means [Q, K, 3], logits [Q, K, C])}."""
    decoder, cfg, D = model.decoder, model.cfg, model.num_dynamic
    query, means = record["query"][None], record["means"][None]
    boxes = None if record["boxes"] is None else record["boxes"][None]
    inputs = keep_inputs(means, record["point_logit"][None], record["box_logit"][None],
                         cfg.pc_range)
    kept, skipped = ranked_queries(decoder.budget_heads.scores_of(query, inputs, D), D, budget)
    kept_dynamic = min(budget.dynamic, D)
    skip = decoder.skip_output(query, means, boxes, skipped, D - kept_dynamic,
                               record["geometry"], record["levels"])
    query, means = gather_queries(query, kept), gather_queries(means, kept)
    boxes = None if boxes is None else gather_queries(boxes, kept[:, :kept_dynamic])
    for layer in decoder.layers[AFTER_LAYER:]:
        query, means, logits, boxes, box_logits = layer(
            query, means, boxes, kept_dynamic, record["geometry"], record["levels"],
            velocity_warp=cfg.motion_compensation, ego_warp=cfg.ego_compensation)
    refined = LayerOutput(means, logits, None, None, None, boxes, box_logits, None,
                          kept_dynamic)
    outputs = {}
    for offset in offsets:
        merged = merged_layer(refined, kept,
                              dataclasses.replace(skip, logits=skip.logits - offset), D)
        outputs[offset] = (merged.means[0], merged.logits[0])
    return outputs


class GridAgreement:
    """How well grids agree with the full model's, streamed over keyframes, no ground truth:
    the mIoU inside the camera mask and the RayIoU of rays cast from RAY_ORIGIN, with the
    full grid as the reference (``result``: both in %, 0 where nothing is occupied)."""

    def __init__(self, cfg):
        self.shape = cfg.grid_shape
        self.voxels, self.rays = MIoU(cfg.num_classes), RayIoU(cfg.num_classes)

    def add(self, grid, full, mask) -> None:
        """grid, full: flat labels [X*Y*Z]; mask [X, Y, Z]."""
        grid, full = grid.view(self.shape).numpy(), full.view(self.shape).numpy()
        self.voxels.add(grid, full, mask.bool().numpy())
        self.rays.add(grid, full, np.array([RAY_ORIGIN]))

    def result(self) -> tuple[float, float]:
        return tuple(100 * float(np.nan_to_num(value)) for value in
                     (self.voxels.miou(), self.rays.result()["RayIoU"]))


@torch.no_grad()
def calibrate_skip_layer(model, files: list[Path], budgets: list[QueryBudget],
                         offsets=SKIP_OFFSETS, progress: bool = True, log=None) -> dict:
    """Lower the skip layer's class logits by the offset (of ``offsets``) whose grids under
    ``budgets`` agree best with the full model's over the cached keyframes (sum of the two
    ``GridAgreement`` values, over the budgets) -> {offset: agreement} and the choice."""
    cfg = model.cfg
    meters = {value: [GridAgreement(cfg) for _ in budgets] for value in offsets}
    for path in tqdm(files, desc="skip offset", disable=not progress):
        record = load_keyframe(path)
        teacher = record["teacher"]
        full, _ = voxelise(teacher["means"][None].float(), teacher["logits"][None].float(),
                           cfg, cfg.num_classes)
        for index, budget in enumerate(budgets):
            outputs = budget_last_layers(model, record, budget, offsets)
            for value, (means, logits) in outputs.items():
                grid, _ = voxelise(means[None].float(), logits[None].float(), cfg,
                                   cfg.num_classes)
                meters[value][index].add(grid[0], full[0], record["mask"])
    agreement = {value: sum(sum(meter.result()) for meter in per_budget)
                 for value, per_budget in meters.items()}
    best = max(offsets, key=lambda value: (agreement[value], -value))
    model.decoder.budget_heads.skip_layer.points.cls[-1].bias.sub_(best)
    if log is not None:
        log("skip layer offset " + ", ".join(f"{v:g}: {a:.2f}" for v, a in agreement.items())
            + f" -> {best:g}")
    return {"agreement": agreement, "offset": best}


@dataclass(frozen=True)
class BudgetHeadTraining:
    """How the heads of ``train_budget_heads`` are fitted (the defaults trained the shipped
    checkpoint's)."""
    skip_epochs: int = 20
    skip_lr: float = 1e-3
    keep_epochs: int = 40
    calibration_keyframes: int = 96    # cached keyframes (evenly spaced) the offset is chosen on
    need_change: float = NEED_CHANGE   # a query predicted to change more is needed by ``auto``
    keyframes_per_file: int | None = None   # None: every keyframe of each infos file


def train_budget_heads(checkpoint, data: list[str], out, cache_dir,
                       options: BudgetHeadTraining = BudgetHeadTraining(),
                       progress: bool = True) -> dict:
    """Train the budget heads of ``checkpoint`` (every other weight frozen) on the keyframes
    of the infos files ``data`` and write the checkpoint with them to ``out``; -> the report
    stored in it under "budget_heads". The model's pass over the keyframes is the slow part
    (about 1.5 s a keyframe on one core for odg_cpu); it is cached in ``cache_dir`` (one file a
    keyframe, a stopped pass resumes), so the heads can be refitted in minutes. Progress is
    appended to OUT.log."""
    out = Path(out)
    with open(f"{out}.log", "a") as log_file:
        def log(text):
            print(f"{time.strftime('%H:%M:%S')} {text}", file=log_file, flush=True)
        model, cfg = load_model(checkpoint)
        payload = read_checkpoint(checkpoint)
        files = []
        for infos in data:
            dataset = OccDataset(infos, cfg, train=False)
            indices = list(range(len(dataset)))[:options.keyframes_per_file]
            start = time.time()
            name = Path(infos).parent.name + "-" + Path(infos).stem
            files += collect(model, dataset, indices, cache_dir, progress, desc=name)
            log(f"model pass over {len(indices)} keyframes of {infos}: "
                f"{time.time() - start:.0f} s")
        init_skip_layer(model)
        skip = fit_skip_layer(model, files, epochs=options.skip_epochs, lr=options.skip_lr,
                              progress=progress, log=log)
        changes, states = refinement_change(model, files, progress)
        keep = fit_keep_scores(model, states, changes, epochs=options.keep_epochs,
                               progress=progress, log=log)
        step = max(1, len(files) // options.calibration_keyframes)
        calibration = calibrate_skip_layer(model, files[::step], budget_ladder(cfg)[1:],
                                           progress=progress, log=log)
        model.decoder.budget_heads.set_trained(
            True, float(squashed(torch.tensor(options.need_change))))
        report = {"source": str(checkpoint), "data": [str(infos) for infos in data],
                  "keyframes": len(files), "need_change": options.need_change,
                  "skip_epochs": options.skip_epochs, "skip_lr": options.skip_lr,
                  "keep_epochs": options.keep_epochs,
                  "skip_layer_loss": skip, "keep_score_loss": keep,
                  "skip_logit_offset": calibration["offset"],
                  "skip_offset_agreement": calibration["agreement"]}
        save_checkpoint(out, model, extra={"budget_heads": report,
                                           **({"export": payload["export"]}
                                              if "export" in payload else {})},
                        compress=payload.get("compression"))
        log(json.dumps(report))
    return report
