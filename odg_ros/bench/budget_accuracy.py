"""Accuracy of query budgets per scene class: the full model, each fixed budget of the ladder,
``query_budget: auto`` (with ``--margins`` also under other margins), the same budgets with
a broken (random) or a hand-made (best point score) ranking, and models with a fixed smaller
query set, all on the same keyframes (the backbone runs once per keyframe; every
configuration decodes its features).

The maintainer script ``python -m tools.eval_budget`` runs it (``--data`` takes CLASS=INFOS
pairs; one plain INFOS path is split into "quiet" and "busy" halves of its scenes by
annotated boxes per keyframe, ``scene_classes``). Scores: mIoU (camera mask) and RayIoU,
grid padded as in ``odg eval``; per configuration also the mean fraction of the queries that
the layers after the budget's layer refined.
"""
from __future__ import annotations

import collections
import time

import numpy as np
import torch
from tqdm import tqdm

from ..data.batch import collate, to_device
from ..data.dataset import OccDataset, load_infos_file
from ..metrics.rayiou import LidarOrigins
from ..metrics.score import OccScore
from ..network.budget import budget_ladder, needed_queries
from ..network.postprocess import box_list
from ..online.budget_policy import BudgetPolicy
from ..train import budget_heads as heads
from ..train.evaluate import predicted_grid
from .sweep import query_budget as smaller_query_set


def scene_classes(infos_path) -> dict[str, dict]:
    """One infos file -> {"quiet": infos, "busy": infos}: its scenes split in two halves by
    annotated boxes per keyframe."""
    infos = load_infos_file(infos_path)
    by_scene = collections.defaultdict(list)
    for info in infos["infos"]:
        by_scene[info["scene_token"]].append(info)
    load = sorted(by_scene, key=lambda s: np.mean([len(i.get("gt_boxes", [])) for i in
                                                   by_scene[s]]))
    half = len(load) // 2
    return {name: {**infos, "infos": [i for s in scenes for i in by_scene[s]]}
            for name, scenes in (("quiet", load[:half]), ("busy", load[half:]))}


class Config:
    """One way to decode: a model, how it picks its budget per keyframe."""

    def __init__(self, name, model, cfg, budget=None, policy=None, scores=None,
                 queries=None, oracle=None):
        self.name, self.model, self.cfg = name, model, cfg
        self.budget, self.policy, self.scores = budget, policy, scores
        self.oracle = oracle                          # a key of oracle_scores
        self.queries = queries or cfg.num_queries     # the full model's, for the fractions
        self.refined, self.milliseconds = [], []

    def decode(self, feats, batch, new_scene: bool, oracles: dict | None = None):
        """``oracles``: this keyframe's ``oracle_scores`` (needed by an oracle config)."""
        if self.policy is not None and new_scene:
            self.policy.reset()
        budget = self.policy.budget if self.policy is not None else self.budget
        budget_heads = self.model.decoder.budget_heads
        original = budget_heads.scores_of
        if self.oracle is not None:
            known = oracles[self.oracle]
            budget_heads.scores_of = lambda query, inputs, num_dynamic: known
        elif self.scores is not None:
            budget_heads.scores_of = self.scores
        try:
            start = time.perf_counter()
            output = self.model.decode(feats, batch["ego2img"], batch["ego_warp"],
                                       batch["time_delta"], budget=budget)
            self.milliseconds.append((time.perf_counter() - start) * 1e3)
        finally:
            budget_heads.scores_of = original
        cfg = self.cfg
        if budget is not None:
            refined = min(budget.static, cfg.static_queries) + min(budget.dynamic,
                                                                    cfg.dynamic_queries)
        else:
            refined = output.last.means.shape[1]
        self.refined.append(refined / self.queries)
        if self.policy is not None:
            need = needed_queries(output.keep_scores, output.num_dynamic,
                                  budget_heads.threshold)[0]
            self.policy.update(int(need[0]), int(need[1]), len(box_list(output, cfg)[0]))
        return output


@torch.no_grad()
def oracle_scores(model, feats, batch) -> dict[str, torch.Tensor]:
    """Perfect rankings of this keyframe's queries (one keyframe, ``Config.decode``'s
    arguments), from one full-budget pass and the skip layer over every query: per query
    "change" [1, Q]: the keep-scores' target (``budget_heads.output_change``, no labels),
    what ideal keep-scores would give; "truth" [1, Q]: the correct voxels refining wins
    (``budget_heads.ground_truth_gain``), the best any ranking after layer 2 could know."""
    decoder, cfg = model.decoder, model.cfg
    capture = heads.DecoderCapture(decoder)
    try:
        output = model.decode(feats, batch["ego2img"], batch["ego_warp"], batch["time_delta"])
    finally:
        capture.remove()
    levels, geometry = capture.inputs[3], capture.inputs[4]
    query, means, _, boxes, _ = capture.after
    everyone = torch.arange(query.shape[1]).unsqueeze(0)
    skipped = decoder.skip_output(query, means, boxes, everyone, model.num_dynamic, geometry,
                                  levels)
    full = (output.last.means[0].float(), output.last.logits[0].float())
    skip = (skipped.means[0].float(), skipped.logits[0].float())
    mask = batch["occ_mask_camera"][0]
    weights = heads.keyframe_class_weights(*full, mask, cfg)
    return {"change": heads.output_change(full, skip, mask, weights, cfg)[None],
            "truth": heads.ground_truth_gain(full, skip, batch["occ_semantics"][0], mask,
                                             cfg)[None]}


def random_scores(seed: int):
    generator = torch.Generator().manual_seed(seed)

    def scores(query, inputs, num_dynamic):
        return torch.rand(query.shape[:2], generator=generator)
    return scores


def point_score(query, inputs, num_dynamic):
    """The hand-made ranking: a dynamic query's best box logit, a static one's best point
    logit (keep_inputs' first two values)."""
    return torch.cat([inputs[:, :num_dynamic, 1], inputs[:, num_dynamic:, 0]], dim=1)


def configurations(model, cfg, include, margins=()) -> list[Config]:
    """margins: also ``auto`` under these margins (``auto-m1.25``; plain ``auto`` has the
    policy's own)."""
    ladder = budget_ladder(cfg)
    configs = [Config("full", model, cfg)]
    for budget in ladder[1:]:
        configs.append(Config(f"keep-{budget.name}", model, cfg, budget=budget))
    configs.append(Config("auto", model, cfg, policy=BudgetPolicy(ladder)))
    for margin in margins:
        configs.append(Config(f"auto-m{margin:g}", model, cfg,
                              policy=BudgetPolicy(ladder, margin=margin)))
    if "oracles" in include:
        for budget in ladder[1:]:
            for kind in ("change", "truth"):
                configs.append(Config(f"oracle-{kind}-{budget.name}", model, cfg,
                                      budget=budget, oracle=kind))
    if "baselines" in include:
        for budget in ladder[1:]:
            configs.append(Config(f"random-{budget.name}", model, cfg, budget=budget,
                                  scores=random_scores(0)))
            configs.append(Config(f"pointscore-{budget.name}", model, cfg, budget=budget,
                                  scores=point_score))
        for fraction in (0.6, 0.35):
            smaller, small_cfg = smaller_query_set(model, cfg, fraction)
            configs.append(Config(f"q{round(fraction * 100)}", smaller, small_cfg,
                                  queries=cfg.num_queries))
    return configs


@torch.no_grad()
def evaluate_class(name, infos, model, cfg, configs, limit=None) -> dict:
    dataset = OccDataset(infos, cfg, train=False)
    origins = LidarOrigins(dataset.infos)
    scores = {c.name: OccScore(dataset.dataset) for c in configs}
    for c in configs:
        c.refined, c.milliseconds = [], []
    previous = None
    indices = list(range(len(dataset)))[:limit]
    for index in tqdm(indices, desc=name):
        batch = to_device(collate([dataset[index]]), "cpu")
        scene = dataset.infos[index]["scene_token"]
        images = batch["images"]
        B, T = images.shape[:2]
        feats = model.extract_features(images.flatten(0, 1))
        frames = [[f.unflatten(0, (B, T))[:, t] for f in feats] for t in range(T)]
        # one full pass for every oracle configuration of this keyframe
        oracles = oracle_scores(model, frames, batch) if any(c.oracle for c in configs) \
            else None
        for c in configs:
            output = c.decode(frames, batch, scene != previous, oracles)
            if not batch["has_occ"][0]:
                continue
            scores[c.name].add(predicted_grid(output, c.cfg), batch["occ_semantics"][0].numpy(),
                               batch["occ_mask_camera"][0].numpy().astype(bool), origins(index))
        previous = scene
    result = {}
    for c in configs:
        r = scores[c.name].result()
        result[c.name] = {"mIoU": r["mIoU"], "RayIoU": r["RayIoU"],
                          "IoU_geometry": r["IoU_geometry"], "samples": r["samples"],
                          "refined_fraction": round(float(np.mean(c.refined)), 4),
                          "decoder_ms": round(float(np.median(c.milliseconds)), 2)}
    return result
