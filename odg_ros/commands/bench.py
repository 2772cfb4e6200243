"""``odg bench``: latency of the online step, the fast paths, and the speed-vs-error sweep.

    odg bench --preset NAME [--device cpu|cuda] [--frames K] [--iters N] [--json]
              [--checkpoint CKPT] [--precision fp32|bf16|fp16] [--no-ring]
    odg bench --compile eager,compiled[,graphs] --preset NAME [--precision fp32,bf16]
              [--data INFOS] [--compiled-step FILE.pt2]
                                                the node's step in each execution mode
    odg bench --fast-paths --preset NAME        each fast path against the plain path
    odg bench --sweep --data INFOS [--checkpoint CKPT] --out DIR [--limit N] [--configs ...]
"""
from __future__ import annotations

import json
import sys

import torch

from ..bench.step import (PRECISIONS, bench_fast_paths, bench_node_step, bench_online_step,
                         data_camera_sets)
from ..config import load_preset
from ..network.precision import resolve_device, slow_precision_warning
from .common import (UserError, device, existing_file, infos_file, nonnegative_int,
                     positive_int, preset)


def add_arguments(parser):
    parser.add_argument("--preset", type=preset, default="odg_t",
                        help="model preset (ignored where --checkpoint gives the model)")
    parser.add_argument("--device", type=device, default="cpu",
                        help="cpu, cuda, cuda:N or auto")
    parser.add_argument("--frames", type=positive_int, default=None,
                        help="history frames K incl. the current one (default: the preset's)")
    parser.add_argument("--iters", type=positive_int, default=None,
                        help="timed iterations, median (default 5; --sweep: 3 per sample)")
    parser.add_argument("--warmup", type=nonnegative_int, default=1, help="untimed steps first")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--checkpoint", default=None, type=existing_file,
                        help="weights (default: random weights of --preset)")
    parser.add_argument("--precision", default="fp32",
                        help=f"one of {', '.join(PRECISIONS)} (fp16 only on CUDA); with "
                             "--compile a comma-separated list, each against the first "
                             "(the node's step stores bf16 / fp16 weights, the others autocast)")
    parser.add_argument("--no-ring", action="store_true",
                        help="re-lay out the cached history every step (no FeatureRing)")
    parser.add_argument("--compile", default=None, metavar="MODES",
                        help="time the node's own step (OnlinePredictor.step) in these "
                             "comma-separated execution modes (eager, compiled, graphs), "
                             "interleaved; the first is the reference (default: not timed by mode)")
    parser.add_argument("--compiled-step", default=None, type=existing_file, metavar="FILE",
                        help="--compile: the compiled and graphs modes run this .pt2 of odg "
                             "export --aoti instead of compiling (default: compile)")
    parser.add_argument("--fast-paths", action="store_true",
                        help="compare each fast path with the plain path (random weights)")
    parser.add_argument("--sweep", action="store_true",
                        help="speed vs error over configurations on a split "
                             "(odg_ros/bench/sweep.py)")
    parser.add_argument("--data", default=None, type=infos_file,
                        help="--sweep: infos of the split (required there); --compile: feed "
                             "the first scene's keyframes instead of random images "
                             "(default: none)")
    parser.add_argument("--occ-root", default=None,
                        help="--sweep: GT root (default: the infos' occ_root)")
    parser.add_argument("--out", default="docs/results",
                        help="--sweep: folder for the JSON and PNG")
    parser.add_argument("--limit", type=positive_int, default=8,
                        help="--sweep: N samples spread evenly over the split")
    parser.add_argument("--configs", default=None,
                        help="--sweep: comma-separated names of default configurations (default: "
                             "all of them), or a "
                             "JSON file with a list of sweep.SweepConfig fields, e.g. "
                             '[{"name": "odg_t", "model": "odg_t"}] (a preset: random '
                             "weights, timing only)")
    parser.add_argument("--list-configs", action="store_true",
                        help="--sweep: print the default configurations and exit")
    parser.add_argument("--no-isolate", action="store_true",
                        help="--sweep: run every configuration in this process (CPU peak "
                             "memory is then the running maximum, not per configuration)")


def run(args) -> int:
    args.device = resolve_device(args.device)
    # fixed shapes, as in the node: cuDNN's measured fastest algorithms (process-wide, so set
    # here where the benchmark starts, as the node's main does)
    torch.backends.cudnn.benchmark = True
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.iters is None:
        args.iters = 3 if args.sweep else 5
    precisions = tuple(p.strip() for p in args.precision.split(",") if p.strip())
    unknown = [p for p in precisions if p not in PRECISIONS]
    if unknown or not precisions or (len(precisions) > 1 and not args.compile):
        raise UserError(f"--precision {args.precision!r}: expected one of {PRECISIONS} "
                        f"(a comma-separated list with --compile)")
    args.precisions = precisions
    if args.sweep:
        return run_sweep_command(args)
    if args.compile:
        return run_compile_command(args)
    if args.fast_paths:
        result = bench_fast_paths(load_preset(args.preset), args.device, args.iters,
                                  args.warmup, progress=not args.json)
        if args.json:
            print(json.dumps(result, indent=2))
            return 0
        print(f"{result['preset']} on {result['device']} ({result['threads']} threads): "
              f"median of {result['iters']} interleaved steps; max |difference| of the last "
              f"layer from '{result['reference']}'")
        print(f"  {'variant':<24}{'backbone':>9}{'decoder':>9}{'post':>7}{'total':>9}"
              f"{'speedup':>8}  {'d means':>9} {'d logits':>9}")
        for name, v in result["variants"].items():
            lat, diff = v["latency_ms"], v["max_abs_diff"]
            print(f"  {name:<24}{lat['backbone']:9.1f}{lat['decoder']:9.1f}"
                  f"{lat['postprocess']:7.1f}{lat['total']:9.1f}{v['speedup_total']:8.2f}"
                  f"  {diff['means']:9.2e} {diff['logits']:9.2e}")
        return 0
    from ..network.checkpoint import load_model
    model, cfg = load_model(args.checkpoint, preset=args.preset, device=args.device)
    result = bench_online_step(cfg, args.device, args.frames, args.iters, args.warmup,
                               progress=not args.json, model=model, ring=not args.no_ring,
                               precision=args.precisions[0])
    result["weights"] = args.checkpoint or "random"
    slow = slow_precision_warning(args.precisions[0], args.device)
    if slow:
        result["warning"] = slow
        print(f"odg bench: {slow}", file=sys.stderr)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    lat = result["latency_ms"]
    print(f"{result['preset']} on {result['device']} ({result['threads']} threads), "
          f"{result['frames']} frames, input {result['input']}, {result['precision']}, "
          f"{'ring' if result['ring'] else 'no ring'}, weights {result['weights']}: "
          f"median of {result['iters']}")
    for stage in ("backbone", "decoder", "postprocess", "total"):
        print(f"  {stage:<12} {lat[stage]:9.1f} ms")
    print(f"  FPS          {result['fps']:9.2f}")
    print(f"  peak memory  {result['peak_memory_mb']:9.0f} MB ({result['memory_method']})")
    layers = result["decoder_layers_ms"]
    if layers:
        parts = [p for p in ("position", "box_position", "attention", "sampling", "mixing",
                             "ffn", "points", "boxes") if any(p in r["parts"] for r in layers)]
        print("  decoder per layer (ms): " + " ".join(f"{p:>9}" for p in parts)
              + f" {'other':>7} {'total':>7}")
        for r in layers:
            print(f"    layer {r['layer']:<15}" + " ".join(
                f"{r['parts'].get(p, 0.0):9.2f}" for p in parts)
                + f" {r['other']:7.2f} {r['total']:7.2f}")
        print(f"    outside the layers (history layout without a ring, Phi MLPs): "
              f"{lat['decoder_outside_layers']:.2f}")
    return 0


def run_compile_command(args) -> int:
    from ..network.checkpoint import load_model
    from ..online.step import MODES
    modes = tuple(m.strip() for m in args.compile.split(",") if m.strip())
    unknown = [m for m in modes if m not in MODES]
    if unknown or not modes:
        raise UserError(f"--compile: unknown mode(s) {unknown}; expected a comma-separated "
                        f"list of {MODES}")
    if "graphs" in modes and args.device != "cuda":
        raise UserError("--compile graphs: CUDA graphs need --device cuda")
    model, cfg = load_model(args.checkpoint, preset=args.preset, device=args.device)
    sets = None
    if args.data:
        try:
            sets = data_camera_sets(args.data, cfg, args.warmup + args.iters)
        except (ValueError, OSError) as error:
            raise UserError(f"--data {args.data}: {error}") from error
    result = bench_node_step(cfg, args.device, modes, args.iters, args.warmup,
                             args.precisions, model, progress=not args.json, sets=sets,
                             compiled_step=args.compiled_step)
    result["weights"] = args.checkpoint or "random"
    result["inputs"] = str(args.data) if args.data else "random"
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{result['preset']} on {result['device']} ({result['threads']} threads), "
          f"{result['frames']} frames, input {result['input']}, weights {result['weights']}, "
          f"images {result['inputs']}: the node's step, median of {result['iters']} "
          f"interleaved sets; agreement and differences against '{result['reference']}' "
          f"over all {result['sets']} sets")
    print(f"  {'variant':<16}{'step ms':>9}{'model':>9}{'upload':>8}{'download':>9}{'FPS':>8}"
          f"{'speedup':>8}{'start-up s':>11}{'grid =':>8}{'occ. =':>8}")
    for name, r in result["modes"].items():
        lat = r["latency_ms"]
        print(f"  {name:<16}{lat['step']:9.1f}{lat['model']:9.1f}{lat['upload']:8.1f}"
              f"{lat['download']:9.1f}{r['fps']:8.2f}{r['speedup']:8.2f}{r['startup_s']:11.1f}"
              f"{r['grid_agreement_min']:8.4f}{r['occupied_agreement_min']:8.4f}")
    for name, r in result["modes"].items():
        if "max_difference" in r:
            print(f"  {name:<16}max |difference|: " + ", ".join(
                f"{key} {value:.3g}" for key, value in r["max_difference"].items()))
    return 0


def run_sweep_command(args) -> int:
    from ..bench.sweep import format_sweep_table, run_sweep, select_configs
    if args.checkpoint is None:
        cfg = load_preset(args.preset)
    else:
        from ..network.checkpoint import load_model
        _, cfg = load_model(args.checkpoint)
    configs = select_configs(args.configs, cfg.num_frames, args.device)
    if args.list_configs:
        for c in configs:
            print(c)
        return 0
    if not args.data:
        raise UserError("--sweep needs --data INFOS")
    if args.checkpoint is None:
        print(f"odg bench --sweep: no --checkpoint, random weights of {args.preset}: the "
              f"timings are real, the scores are not")
    report = run_sweep(args.data, args.checkpoint, args.preset, args.device, configs,
                       limit=args.limit, repeats=args.iters, warmup=args.warmup,
                       threads=args.threads, isolate=False if args.no_isolate else None,
                       out=args.out, occ_root=args.occ_root, progress=not args.json)
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    print(format_sweep_table(report))
    for path in report.get("files", []):
        print(f"wrote {path}")
    return 0
