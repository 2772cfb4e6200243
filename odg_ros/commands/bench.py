"""``odg bench``: the node's own step per camera set, and its speed against error.

    odg bench [--checkpoint CKPT | --preset NAME] [--device cpu|cuda] [--frames K]
              [--iters N] [--compile MODES] [--precision P[,P]] [--query-budget B]
              [--no-visibility] [--data INFOS] [--compiled-step FILE.pt2] [--json]
    odg bench --shares [--checkpoint CKPT] [--data INFOS] [--threads N] [--iters N]
    odg bench --sweep --data INFOS [--checkpoint CKPT] [--out DIR] [--limit N] [--configs ...]

Both time ``OnlinePredictor.step``, what the node runs per camera set (odg_ros/bench/step_timing.py,
odg_ros/bench/sweep.py), at the node's settings unless an option says otherwise.
"""
from __future__ import annotations

import json
import sys

import torch

from .common import (UserError, add_device_option, add_json_option, add_preset_option,
                     existing_file, infos_file, nonnegative_int, positive_int)

SWEEP_OUT = "bench_results"


EPILOG = """\
What is timed: OnlinePredictor.step, the node's own step per camera set (geometry packed and
images uploaded, backbone on the newest set, decoder over the feature ring, grid with
padding, ranked boxes, visibility, results back), at the node's settings
(config/odg_node.schema.yaml) unless an option above says otherwise. FPS = 1000 / step ms;
"model" is its device part, the node's stage_model_ms. Stages and decoder layers come from
marks inside that step, recorded on steps of their own of an eager variant; a compiled or
graph-replayed step has no marks inside and is timed whole. Each variant's grid, confidence
and boxes are compared with an eager fp32 step on the same camera sets."""


def add_arguments(parser):
    parser.epilog = EPILOG
    parser.add_argument("--checkpoint", default=None, type=existing_file,
                        help="weights (default: the shipped model/odg_cpu.pt, as the node)")
    add_preset_option(parser, default=None,
                      help="random weights of this preset instead of a checkpoint (timing "
                           "only; default: none, the checkpoint's model)")
    add_device_option(parser, default="cpu")
    parser.add_argument("--frames", type=positive_int, default=None,
                        help="history frames K incl. the current one (default: the model's)")
    parser.add_argument("--iters", type=positive_int, default=None,
                        help="timed steps, median (default 5, and as many recorded by the "
                             "step's marks; --sweep: 3 per sample)")
    parser.add_argument("--warmup", type=nonnegative_int, default=1, help="untimed steps first")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch CPU threads (default: torch's choice)")
    add_json_option(parser)
    parser.add_argument("--compile", default=None, metavar="MODES",
                        help="execution modes of the step, comma-separated (auto, eager, "
                             "compiled, graphs), taking turns set by set; the first is what "
                             "speed-ups are against (default: the node's compile setting, "
                             "auto: graphs on CUDA, eager on the CPU)")
    parser.add_argument("--precision", default=None,
                        help="auto, fp32, bf16-encoder, bf16 or fp16 (CUDA), or a "
                             "comma-separated list: a variant each (default: the node's "
                             "precision setting, auto: bf16-encoder on a CPU with bf16 "
                             "instructions, else fp32)")
    parser.add_argument("--query-budget", default=None, metavar="BUDGET",
                        help="full, auto or a fraction of the queries (default: the node's "
                             "query_budget setting, full)")
    parser.add_argument("--no-visibility", action="store_true",
                        help="the step without the voxels the cameras observe (the node's "
                             "visibility false)")
    parser.add_argument("--compiled-step", default=None, type=existing_file, metavar="FILE",
                        help="the compiled and graphs modes run this .pt2 of odg export "
                             "--aoti instead of compiling (default: compile)")
    parser.add_argument("--data", default=None, type=infos_file,
                        help="feed the first scene's keyframes (default: random images); "
                             "--sweep: the split to score (required there)")
    parser.add_argument("--shares", action="store_true",
                        help="instead: the padding's and the visibility's shares of the "
                             "step's CPU time, by the step's marks and by the step without "
                             "each, side by side (odg_ros/bench/stage_shares.py; one thread "
                             "unless --threads; --iters sets, default 8)")
    parser.add_argument("--sweep", action="store_true",
                        help="speed against error over configurations of the step on a "
                             "split (odg_ros/bench/sweep.py)")
    parser.add_argument("--occ-root", default=None,
                        help="--sweep: GT root (default: the infos' occ_root)")
    parser.add_argument("--out", default=SWEEP_OUT,
                        help="--sweep: folder for bench_<device>.json and .png")
    parser.add_argument("--limit", type=positive_int, default=8,
                        help="--sweep: N samples spread evenly over the split")
    parser.add_argument("--configs", default=None,
                        help="--sweep: comma-separated names of default configurations (default: "
                             "all of them, see --list-configs), or a JSON file with a list of "
                             'sweep.SweepConfig fields, e.g. [{"name": "odg_t", "model": '
                             '"odg_t"}] (a preset: random weights, timing only)')
    parser.add_argument("--list-configs", action="store_true",
                        help="--sweep: print the default configurations of the model given "
                             "and exit")
    parser.add_argument("--no-isolate", action="store_true",
                        help="--sweep: run every configuration in this process (CPU peak "
                             "memory is then the running maximum, not per configuration)")


def weights_path(args) -> str:
    """--checkpoint, or the shipped checkpoint (the node's default)."""
    from ..resources import shipped_checkpoint
    return args.checkpoint or str(shipped_checkpoint())


def _load(args):
    """-> (model, cfg, what the weights are) of --checkpoint / --preset / the shipped file."""
    from ..network.checkpoint import load_model
    if args.checkpoint and args.preset:
        raise UserError("--checkpoint and --preset: give one (a preset means random weights)")
    if args.preset:
        model, cfg = load_model(None, preset=args.preset, device=args.device)
        return model, cfg, f"random weights of {args.preset}"
    path = weights_path(args)
    model, cfg = load_model(path, device=args.device)
    return model, cfg, path


def _variants(args) -> tuple[tuple, tuple]:
    from ..network.precision import NODE_PRECISIONS
    from ..online.step import MODES
    modes = tuple(m.strip() for m in (args.compile or "").split(",") if m.strip())
    unknown = [m for m in modes if m not in ("auto",) + MODES]
    if unknown or (args.compile is not None and not modes):
        raise UserError(f"--compile: unknown mode(s) {unknown}; expected a comma-separated "
                        f"list of auto, {', '.join(MODES)}")
    if "graphs" in modes and torch.device(args.device).type != "cuda":
        raise UserError("--compile graphs: CUDA graphs need --device cuda")
    precisions = tuple(p.strip() for p in (args.precision or "").split(",") if p.strip())
    unknown = [p for p in precisions if p not in NODE_PRECISIONS]
    if unknown or (args.precision is not None and not precisions):
        raise UserError(f"--precision {args.precision!r}: expected one of {NODE_PRECISIONS} or a "
                        "comma-separated list of them")
    return modes or None, precisions or None


def run(args) -> int:
    from ..network.precision import resolve_device
    args.device = resolve_device(args.device)
    # fixed shapes, as in the node: cuDNN's measured fastest algorithms (process-wide, so set
    # here where the benchmark starts, as the node's main does)
    torch.backends.cudnn.benchmark = True
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.iters is None:
        args.iters = 3 if args.sweep else 8 if args.shares else 5
    if args.sweep:
        return run_sweep_command(args)
    if args.shares:
        return run_shares_command(args)
    return run_step_command(args)


def run_step_command(args) -> int:
    from ..bench.step_timing import bench_node_step, data_camera_sets, node_settings
    from ..network.precision import slow_precision_warning
    modes, precisions = _variants(args)
    settings = node_settings(query_budget=args.query_budget,
                             visibility=False if args.no_visibility else None)
    model, cfg, weights = _load(args)
    sets = None
    if args.data:
        try:
            sets = data_camera_sets(args.data, cfg)
        except (ValueError, OSError) as error:
            raise UserError(f"--data {args.data}: {error}") from error
    result = bench_node_step(cfg, args.device, modes, args.iters, args.warmup, precisions,
                             model, progress=not args.json, sets=sets,
                             compiled_step=args.compiled_step, frames=args.frames,
                             settings=settings)
    result["weights"] = weights
    result["inputs"] = str(args.data) if args.data else "random"
    # one line per precision that runs slower than fp32 here, on stderr and in the JSON
    slow = [w for w in (slow_precision_warning(p, args.device) for p in result["precisions"])
            if w]
    for warning in slow:
        print(f"odg bench: {warning}", file=sys.stderr)
    if slow:
        result["warnings"] = slow
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_step_result(result))
    return 0


def run_shares_command(args) -> int:
    from ..bench.stage_shares import SHARED_STAGES, format_shares, stage_shares
    from ..bench.step_timing import data_camera_sets, node_inputs, node_settings
    if torch.device(args.device).type != "cpu":
        raise UserError("--shares: CPU time shares, --device cpu only")
    if args.no_visibility or args.compile or args.precision and "," in args.precision:
        raise UserError("--shares times the node's step with and without each stage: no "
                        "--no-visibility, --compile or several precisions")
    settings = node_settings(query_budget=args.query_budget, precision=args.precision)
    model, cfg, weights = _load(args)
    count = args.warmup + args.iters
    try:
        sets = data_camera_sets(args.data, cfg, count) if args.data else \
            node_inputs(cfg, count)
    except (ValueError, OSError) as error:
        raise UserError(f"--data {args.data}: {error}") from error
    sets = [sets[i % len(sets)] for i in range(count)]
    stages = SHARED_STAGES if cfg.occupancy_padding else ("visibility",)
    try:
        result = stage_shares(model, cfg, sets, settings, stages, threads=args.threads or 1,
                              warmup=args.warmup, progress=not args.json)
    except ValueError as error:
        raise UserError(f"--shares: {error}") from error
    result.update(weights=weights, inputs=str(args.data) if args.data else "random")
    print(json.dumps(result, indent=2) if args.json else
          f"{cfg.name} ({weights}), images {result['inputs']}\n" + format_shares(result))
    return 0


def format_step_result(result: dict) -> str:
    s = result["settings"]
    lines = [
        f"{result['preset']} ({result['weights']}) on {result['device']} ({result['threads']} "
        f"threads), {result['frames']} frames, input {result['input']}, images "
        f"{result['inputs']}",
        f"the node's step (OnlinePredictor.step) at query_budget {s['query_budget']}, "
        f"visibility {'on' if s['visibility'] else 'off'}, padding "
        f"{'on' if s['padding'] else 'off'}; median of {result['iters']} steps per variant "
        f"after {result['warmup']} warm-up, the variants taking turns; grid and boxes "
        f"against {result['reference']}",
        f"  {'variant':<16}{'step ms':>9}{'model':>9}{'upload':>8}{'download':>9}{'FPS':>8}"
        f"{'speedup':>8}{'start-up s':>11}{'grid =':>8}{'occ. =':>8}"]
    # per variant: its row of the table, then its differences, then its stages
    rows, differences, stages = [], [], []
    for name, r in result["modes"].items():
        lat = r["latency_ms"]
        rows.append(f"  {name:<16}{lat['step']:9.1f}{lat['model']:9.1f}{lat['upload']:8.1f}"
                    f"{lat['download']:9.1f}{r['fps']:8.2f}{r['speedup']:8.2f}"
                    f"{r['startup_s']:11.1f}{r['grid_agreement_min']:8.4f}"
                    f"{r['occupied_agreement_min']:8.4f}")
        if name != result["reference"]:
            d = r["max_difference"]
            differences.append(
                f"  {name:<16}largest differences: confidence {d['confidence']}/255, boxes "
                f"unmatched {d['boxes_unmatched']} (of {d['boxes_valid']}), box centre "
                f"{d['box_centre_m']:.3g} m, size {d['box_size_m']:.3g} m, score "
                f"{d['box_score']:.3g}")
        stages += format_stages(name, r)
    lines += rows + differences + stages
    lines.append(f"  peak memory {result['peak_memory_mb']:.0f} MB ({result['memory_method']})")
    return "\n".join(lines)


def format_stages(name: str, r: dict) -> list[str]:
    """The stages and decoder layers of one variant (from its marks), or why there are none."""
    lat = r["latency_ms"]
    if r["stages"] != "marks":
        return [f"  {name}: {r['stages']} (stages: time an eager variant)"]
    from ..online.marks import LAYER_PARTS, STEP_STAGES
    lines = [f"  {name}, stages (ms, the step's marks, median over the recorded steps): "
             + ", ".join(f"{k} {lat[k]:.1f}" for k in STEP_STAGES if k in lat)]
    layers = r["decoder_layers_ms"]
    if layers:
        parts = [p for p in LAYER_PARTS if any(p in row["parts"] for row in layers)]
        lines.append("    decoder per layer (ms): " + " ".join(f"{p:>9}" for p in parts)
                     + f" {'other':>7} {'total':>7}")
        for row in layers:
            lines.append(f"      layer {row['layer']:<15}" + " ".join(
                f"{row['parts'].get(p, 0.0):9.2f}" for p in parts)
                + f" {row['other']:7.2f} {row['total']:7.2f}")
        lines.append(f"      outside the layers (queries, Phi MLPs, keep-scores): "
                     f"{lat['decoder_outside_layers']:.2f}")
    return lines


def run_sweep_command(args) -> int:
    from ..bench.sweep import format_sweep_table, model_config, run_sweep, select_configs
    if args.checkpoint and args.preset:
        raise UserError("--checkpoint and --preset: give one (a preset means random weights)")
    checkpoint = None if args.preset else weights_path(args)
    weights = checkpoint or f"random weights of {args.preset}"
    cfg = model_config(checkpoint, args.preset)
    try:
        configs = select_configs(args.configs, cfg.num_frames, args.device)
    except ValueError as error:
        raise UserError(f"--configs: {error}") from error
    if args.list_configs:
        print(f"default configurations of {cfg.name} ({weights}):")
        for c in configs:
            print(f"  {c.describe()}")
        return 0
    if not args.data:
        raise UserError("--sweep needs --data INFOS")
    if checkpoint is None:
        print(f"odg bench --sweep: {weights}: the timings are real, the scores are not")
    report = run_sweep(args.data, checkpoint, args.preset or cfg.name, args.device, configs,
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
