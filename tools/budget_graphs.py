"""Query budgets replayed as CUDA graphs: the node's own predictor with ``query_budget`` full,
auto (one graph per rung of the ladder) and two fixed fractions, each graph against the eager
step of its budget, and the decoder's time at each rung.

    python -m tools.budget_graphs --preset odg_t odg_l [--precision bf16] [--iters 20]
        [--json OUT]

The model has random weights and its budget heads are random too, flagged trained (ODG-T and
ODG-L ship no trained heads): a rung's time does not depend on the weights, only on how many
queries the later layers refine, which the rung fixes. What ``auto`` saves on a class of scene
depends on which rungs its keep-scores choose there; the one measurement of that is the
shipped odg_cpu on the held-out open-road world (``OPEN_ROAD_SHARES``). So "auto on the open
road" here is the decoder's time at each rung, weighted by the share of the keyframes that
``auto`` ran at that rung there, against the full decoder.

The graphs are captured around the eager step (no compile: each budget would be a compile of
minutes on a bare machine), with the predictor's own capture (``CudaGraphStep``, one per
budget): what is checked is the capture and replay per budget, the static buffers and the
switching between rungs; the kernels are eager ones, so the times are those of the eager
kernels without launch overhead. On the CPU (``--device cpu``: a dry run of the plumbing at a
small size) the graphs are ``testing.online.RecordedGraph``, which replays the recorded ops.

Times: medians of ``--iters`` steps, the budgets taking turns step by step; CUDA events.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import time

import torch

from odg_ros.model_config import load_preset
from odg_ros.network import ODG
from odg_ros.network.budget import budget_ladder
from odg_ros.network.precision import precision_context
from odg_ros.online import predictor as predictor_module
from odg_ros.online.predictor import OnlinePredictor
from tools.gpu_tool import parse_args, write_json

# The share of the keyframes at each rung of the ladder (full, middle, smallest) that
# ``query_budget auto`` ran with the shipped odg_cpu on the held-out open-road world
# (odg synth --scenes 4 --seconds 4 --seed 9104 --roads open-road; odg eval --query-budget
# auto: keyframes per budget 4 / 19 / 9 of 32; 55.9 % of the queries refined).
OPEN_ROAD_SHARES = (4 / 32, 19 / 32, 9 / 32)
FIXED_FRACTIONS = ("0.6", "0.35")


def graph_step_class(device: torch.device):
    if device.type == "cuda":
        return predictor_module.CudaGraphStep
    from testing.online import RecordedGraph      # the CPU stand-in (a dry run)
    return RecordedGraph


@contextlib.contextmanager
def graph_steps(device):
    """Within it the predictor captures with ``graph_step_class(device)``."""
    original = predictor_module.CudaGraphStep
    predictor_module.CudaGraphStep = graph_step_class(device)
    try:
        yield
    finally:
        predictor_module.CudaGraphStep = original


def predictor_of(model, cfg, device, precision, query_budget, graphs: bool):
    """The node's predictor at ``query_budget``; ``graphs``: its step captured per budget
    into graphs of the eager step (the predictor's own capture, without the compile)."""
    predictor = OnlinePredictor(model, cfg, device, max_gap=10.0, precision=precision,
                                query_budget=query_budget)
    if graphs:
        predictor.mode = "graphs"
        with graph_steps(device):
            predictor._warm_up()
        assert len(predictor._graphs) == len(predictor.budgets)
    return predictor


def camera_sets(cfg, count: int, seed: int = 0):
    from testing.online import make_sets
    return make_sets(cfg, count, seed)


def step_at(predictor, camera_set, level=None):
    """One step; ``level``: the rung of ``auto`` to run (the policy's choice set aside)."""
    if level is not None:
        predictor.policy.level = level
    return predictor.step(*camera_set)


def agreement(graphs, eager, sets, levels) -> float:
    """The smallest share of voxels whose label the graph step and the eager step agree on,
    over ``sets`` (each at its rung in ``levels``)."""
    worst = 1.0
    for camera_set, level in zip(sets, levels):
        a, b = step_at(graphs, camera_set, level), step_at(eager, camera_set, level)
        assert a.query_budget == b.query_budget, (a.query_budget, b.query_budget)
        worst = min(worst, float((a.grid == b.grid).mean()))
    return worst


def decoder_function(predictor, budget):
    """f(images, packed) -> the last layer's means and logits: the decoder of the predictor's
    step over its ring, at ``budget``."""
    step = predictor.online_step

    def decode(images, packed):
        ego2img, warps, deltas, frame_index, _ = step.layout.unpack(packed)
        with precision_context(step.precision, step.device):
            output = step.model.decode_stored(step.ring.all_levels(), ego2img, warps, deltas,
                                              frame_index, False, budget=budget)
        return output.last.means, output.last.logits
    return decode


def timed_ms(run, device) -> float:
    if device.type == "cuda":
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        run()
        end.record()
        end.synchronize()
        return start.elapsed_time(end)
    start = time.perf_counter()
    run()
    return 1e3 * (time.perf_counter() - start)


def measure(preset: str, args) -> dict:
    device = torch.device(args.device)
    overrides = {}
    if args.image_size:
        overrides["image_size"] = tuple(args.image_size)
    if args.frames:
        overrides["num_frames"] = args.frames
    cfg = load_preset(preset, **overrides)
    torch.manual_seed(0)
    model = ODG(cfg).to(device).eval()
    model.decoder.budget_heads.set_trained(True, 0.0)     # random heads (see the docstring)
    ladder = budget_ladder(cfg)
    sets = camera_sets(cfg, cfg.num_frames + 3)
    rungs = [b.name for b in ladder]
    result = {"preset": cfg.name, "precision": args.precision, "device": str(device),
              "device_name": torch.cuda.get_device_name(device) if device.type == "cuda"
              else "cpu", "torch": torch.__version__, "queries": cfg.num_queries,
              "input": [cfg.num_cams, 3, *cfg.image_size], "frames": cfg.num_frames,
              "ladder": rungs, "refined": {b.name: round(b.refined_fraction(cfg), 3)
                                           for b in ladder},
              "graphs": "captured around the eager step (no compile)", "predictors": {}}
    settings = {"full": [None], "auto": list(range(len(ladder)))}
    settings.update({f: [None] for f in FIXED_FRACTIONS})
    predictors = {}
    with torch.inference_mode():
        for setting, levels in settings.items():
            graphs = predictor_of(model, cfg, device, args.precision, setting, True)
            eager = predictor_of(model, cfg, device, args.precision, setting, False)
            turns = [levels[i % len(levels)] if setting == "auto" else None
                     for i in range(len(sets))]
            result["predictors"][setting] = {
                "budgets": [graphs._budget_name(b) for b in graphs.budgets],
                "captures": len(graphs._graphs),
                "grid_agreement_min": agreement(graphs, eager, sets, turns)}
            del eager
            predictors[setting] = graphs
            print(f"budget_graphs: {setting}: {result['predictors'][setting]}", flush=True)
        # whole steps, every budget taking turns: full, each rung of auto, the fractions
        turns = [("full", None)] + [("auto", i) for i in range(len(ladder))] + \
            [(f, None) for f in FIXED_FRACTIONS]
        times = {turn: [] for turn in turns}
        for i in range(args.warmup + args.iters):
            for setting, level in turns:
                p = predictors[setting]
                prediction = step_at(p, sets[i % len(sets)], level)
                if i >= args.warmup:
                    times[(setting, level)].append(1e3 * prediction.timings["model"])
        for (setting, level), ms in times.items():
            entry = result["predictors"][setting]
            name = rungs[level] if level is not None else entry["budgets"][0]
            entry.setdefault("step_ms", {})[name] = round(statistics.median(ms), 3)
        # the decoder alone at each budget, over the full predictor's ring
        full = predictors["full"]
        graph_step = graph_step_class(device)
        decoders = {"full": graph_step(decoder_function(full, None), full._images,
                                       full._packed, device)}
        decoders.update({b.name: graph_step(decoder_function(full, b), full._images,
                                            full._packed, device) for b in ladder})
        decoder_times = {name: [] for name in decoders}
        for i in range(args.warmup + args.iters):
            for name, graph in decoders.items():
                ms = timed_ms(graph.replay, device)
                if i >= args.warmup:
                    decoder_times[name].append(ms)
    decoder_ms = {name: statistics.median(ms) for name, ms in decoder_times.items()}
    result["decoder_ms"] = {name: round(ms, 3) for name, ms in decoder_ms.items()}
    shares = dict(zip(rungs, args.rung_shares))
    auto_ms = sum(share * decoder_ms[name] for name, share in shares.items())
    result["open_road"] = {
        "rung_shares": shares, "refined": round(sum(
            share * result["refined"][name] for name, share in shares.items()), 3),
        "auto_decoder_ms": round(auto_ms, 3), "full_decoder_ms": result["decoder_ms"]["full"],
        "speedup": round(decoder_ms["full"] / auto_ms, 3),
        "shares_from": "the shipped odg_cpu's auto on the held-out open-road world"}
    if device.type == "cuda":
        result["peak_memory_gib"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", nargs="+", default=["odg_t"],
                        help="model presets, one after the other (random weights)")
    parser.add_argument("--precision", default="bf16", choices=("fp32", "bf16", "fp16"))
    parser.add_argument("--device", default="cuda", choices=("cuda", "cpu"),
                        help="cuda; cpu: a dry run with the graph stand-in")
    parser.add_argument("--image-size", type=int, nargs=2, metavar=("H", "W"),
                        help="network input (default: the preset's)")
    parser.add_argument("--frames", type=int, help="history frames (default: the preset's)")
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--rung-shares", type=float, nargs=3, default=OPEN_ROAD_SHARES,
                        metavar=("FULL", "MIDDLE", "SMALLEST"),
                        help="share of the steps at each rung for the auto figure (default: "
                             "the open road's)")
    args = parse_args(parser, argv, "budget_graphs", "--device cpu: a dry run")
    if args is None:
        return 2
    if abs(sum(args.rung_shares) - 1.0) > 1e-6:
        parser.error("--rung-shares must add up to 1")
    if args.device == "cuda":
        torch.backends.cudnn.benchmark = True            # as the node sets it
    results = []
    for preset in args.preset:
        results.append(measure(preset, args))
        print(json.dumps(results[-1], indent=1))
        write_json(args.json, results)          # each preset as soon as it is measured
        road = results[-1]["open_road"]
        print(f"budget_graphs: {preset} decoder, full {road['full_decoder_ms']:.2f} ms, auto on "
              f"the open road {road['auto_decoder_ms']:.2f} ms: {road['speedup']:.2f}x",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
