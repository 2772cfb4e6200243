"""Where the node's step spends its time, per stage and per decoder layer part, at each query
budget of the ladder (network/budget.py) and of fixed smaller query sets (every layer on fewer
queries), and what a smaller budget saves: milliseconds (the node's step, ``OnlinePredictor``,
one per budget, timed and recorded by its marks as ``odg bench`` does: medians, the budgets
taking turns step by step in one process, so a busy machine slows them alike), ATen ops and
FLOPs per part of the decoder.

The maintainer script ``python -m tools.profile_budget`` runs it on random weights (timing
only; ``--checkpoint`` for a trained model of the first preset); the budget heads are marked trained so that every budget runs. The backbone does not depend on
the budget: its median is over every budget's steps. FLOPs: torch's counter (matrix
products, convolutions, attention) plus bilinear grid sampling at 8 FLOPs per channel and
point.
"""
from __future__ import annotations

import collections
import statistics

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import flop_registry, shape_wrapper

from .step_timing import (Variant, node_inputs, node_predictor, node_settings,
                                stage_summary, take_turns)
from .sweep import query_budget
from ..network.budget import budget_ladder
from ..online.marks import LAYER_PARTS
from .census import Census, CensusMode

aten = torch.ops.aten
# decoder source files -> the part of a layer they hold (census lines are per file)
PART_FILES = {"das_attention.py": "attention", "sampling.py": "sampling",
              "mixing.py": "mixing", "gaussian_heads.py": "heads", "box_head.py": "heads",
              "budget.py": "budget", "decoder.py": "other", "queries.py": "other",
              "grid_range.py": "other", "odg.py": "other",
              "rotation.py": "heads"}       # the Gaussian heads' quaternion normalising
OUTSIDE = "outside the decoder"      # backbone, ring, grid, boxes, visibility: not in totals
PART_NAMES = {"points": "heads", "boxes": "heads", "box_position": "position"}
FIXED_SETS = (0.6, 0.35)           # fractions of the queries of the fixed smaller sets timed


def grid_sample_flops(input_shape, grid_shape, *args, out_shape=None, **kwargs) -> int:
    """Bilinear: 4 taps, a multiply and an add each, per channel and output point."""
    return 8 * input_shape[0] * input_shape[1] * grid_shape[1] * grid_shape[2]


FLOPS = {**flop_registry, aten.grid_sampler_2d: shape_wrapper(grid_sample_flops)}


class PartFlops(TorchDispatchMode):
    """FLOPs per decoder part: torch's formulas, attributed to the part whose forward is
    running (forward hooks on the decoder, every layer part and the budget heads set
    ``part``; outside the decoder: OUTSIDE)."""

    def __init__(self, decoder):
        super().__init__()
        self.flops, self.part, self.handles = collections.Counter(), OUTSIDE, []
        self._hook(decoder, "other", after=OUTSIDE)
        for layer in decoder.layers:
            for name in LAYER_PARTS:
                if getattr(layer, name, None) is not None:
                    self._hook(getattr(layer, name), PART_NAMES.get(name, name))
        for head in decoder.budget_heads.children():
            self._hook(head, "budget")

    def _hook(self, module, name, after="other"):
        def pre(*_):
            self.part = name

        def post(*_):
            self.part = after
        self.handles += [module.register_forward_pre_hook(pre),
                         module.register_forward_hook(post)]

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        formula = FLOPS.get(func.overloadpacket)
        if formula is not None:
            self.flops[self.part] += formula(*args, **kwargs, out_val=out)
        return out

    def __exit__(self, *exc):
        for handle in self.handles:
            handle.remove()
        return super().__exit__(*exc)


def flops_by_part(decoder, run) -> dict[str, float]:
    """GFLOPs of ``run()`` per part of ``decoder``; ``total``: the decoder's."""
    with PartFlops(decoder) as counter:
        run()
    parts = dict(counter.flops)
    parts["total"] = sum(v for k, v in counter.flops.items() if k != OUTSIDE)
    return {k: round(v / 1e9, 4) for k, v in parts.items()}


def ops_by_part(run) -> dict[str, float]:
    census = Census()
    with CensusMode(census, device_type=None):
        run()
    parts = collections.Counter()
    for (_, line), n in census.ops.items():
        file = line.split(":")[0].split("/")[-1]
        parts[PART_FILES.get(file, OUTSIDE)] += n
    parts["total"] = sum(n for part, n in parts.items() if part != OUTSIDE)
    parts["host_syncs"] = sum(census.syncs.values())
    return dict(parts)


def profile_preset(cfg, model, iters: int, warmup: int, progress: bool = True) -> dict:
    """Long because it builds, runs and tabulates every budget's step in one place."""
    model.decoder.budget_heads.set_trained(True)
    budgets = budget_ladder(cfg)
    settings = node_settings()
    variants = {b.name: Variant(b.name, "eager", settings["precision"], node_predictor(
        model, cfg, "cpu", {**settings, "query_budget": b}, mode="eager")) for b in budgets}
    # the alternative a budget must beat: a model with fewer queries in every layer
    fixed = [f"q{round(100 * f)}" for f in FIXED_SETS]
    for name, fraction in zip(fixed, FIXED_SETS):
        smaller, smaller_cfg = query_budget(model, cfg, fraction)
        variants[name] = Variant(name, "eager", settings["precision"], node_predictor(
            smaller, smaller_cfg, "cpu", {**settings, "query_budget": "full"}, mode="eager"))
    sets = node_inputs(cfg, warmup + 2 * iters)
    take_turns(variants, sets, warmup, iters, cfg, progress=progress)
    rows, full = [], None
    for budget in budgets:
        variant = variants[budget.name]
        medians = variant.recorder.medians()
        stages = stage_summary(medians, cfg.num_layers)

        predictor = variant.predictor

        @torch.no_grad()        # not inference mode: there linear, conv2d, attention reach a
        def run():              # dispatch mode whole, and torch's FLOP formulas miss them
            predictor.online_step(torch.from_numpy(sets[0][0]), predictor._packed,
                                  predictor.budget)
        decoder = predictor.online_step.model.decoder
        flops, ops = flops_by_part(decoder, run), ops_by_part(run)
        row = {"budget": budget.name, "static": budget.static, "dynamic": budget.dynamic,
               "queries_refined": budget.static + budget.dynamic,
               "step_ms": round(statistics.median(variant.times["step"]), 2),
               "decoder_ms": round(medians["decoder"], 2),
               "postprocess_ms": stages["latency_ms"]["postprocess"],
               "decoder_layers_ms": stages["decoder_layers_ms"],
               "budget_ms": budget_parts(medians), "gflops": flops, "ops": ops}
        full = full or row
        row["decoder_vs_full"] = round(row["decoder_ms"] / full["decoder_ms"], 3)
        row["gflops_vs_full"] = round(flops["total"] / full["gflops"]["total"], 3)
        rows.append(row)
    fixed_rows = [{"fixed_set": name,
                   "decoder_ms": round(variants[name].recorder.medians()["decoder"], 2)}
                  for name in fixed]
    for row in fixed_rows:
        row["decoder_vs_full"] = round(row["decoder_ms"] / full["decoder_ms"], 3)
    backbone = [variants[b.name].recorder.medians()["backbone"] for b in budgets]
    return {"preset": cfg.name, "queries": cfg.num_queries, "frames": cfg.num_frames,
            "input": [cfg.num_cams, 3, *cfg.image_size], "threads": torch.get_num_threads(),
            "iters": iters, "backbone_ms": round(statistics.median(backbone), 2),
            "settings": {k: v for k, v in settings.items() if k != "query_budget"},
            "budgets": rows, "fixed_sets": fixed_rows}


def budget_parts(medians: dict[str, float]) -> dict:
    """The budget's own cost: keep-scores and the skip layer (total and per part), ms."""
    return {name.replace("skip_layer.", "skip."): round(ms, 3) for name, ms in medians.items()
            if name.startswith(("skip_layer", "keep_"))}


def summary(result: dict) -> dict:
    """Per budget: decoder ms, its ratio to full, and ms per part summed over the layers."""
    rows = {}
    for row in result["budgets"]:
        parts = collections.Counter()
        for layer in row["decoder_layers_ms"]:
            for part, ms in layer["parts"].items():
                parts[part] += ms
        rows[row["budget"]] = {"decoder_ms": row["decoder_ms"], "vs_full": row["decoder_vs_full"],
                               "gflops_vs_full": row["gflops_vs_full"],
                               "parts_ms": {k: round(v, 1) for k, v in parts.items()},
                               "layers_ms": [round(r["total"], 1)
                                             for r in row["decoder_layers_ms"]],
                               "budget_ms": row["budget_ms"]}
    return {"preset": result["preset"], "backbone_ms": result["backbone_ms"], "budgets": rows,
            "fixed_sets": {r["fixed_set"]: r["decoder_vs_full"] for r in result["fixed_sets"]}}
