"""``odg profile train --preset P --data INFOS [--cuda-paths]``: the ops a training step
launches and the host syncs it makes, by phase and by source line (odg_ros/bench/census.py);
on a GPU also the kernel time against the wall time of a step."""
from __future__ import annotations

import json
import logging
import tempfile
import time
from pathlib import Path

import torch

from ..model_config import load_preset
from ..data.batch import collate
from ..bench.census import PHASES, census_of_steps
from ..train.trainer import Trainer, TrainOptions, training_renderer
from .common import (add_backbone_start_options, add_device_option, add_preset_option,
                     add_render_pixels_option, infos_file, positive_int)


def add_arguments(parser):
    parser.add_argument("what", choices=("train",), help="what to profile: a training step")
    add_preset_option(parser)
    parser.add_argument("--data", required=True, type=infos_file,
                        help="training infos (odg prepare)")
    add_device_option(parser, default="cpu")
    parser.add_argument("--cuda-paths", action="store_true",
                        help="take the code paths of a CUDA run and count every op as a GPU op "
                             "(the census of a GPU step, taken on the CPU)")
    parser.add_argument("--image-size", type=positive_int, nargs=2, metavar=("H", "W"),
                        help="network input size (the counts do not depend on it; default: "
                             "the preset's)")
    parser.add_argument("--frames", type=positive_int,
                        help="frames per sample, the current one included (the waits do not "
                             "depend on it; default: the preset's)")
    parser.add_argument("--batch-size", type=positive_int, default=1, help="samples per step")
    parser.add_argument("--renderer", choices=("torch", "gsplat"), default="torch",
                        help="the render loss's renderer: ours, or gsplat's (with --cuda-paths "
                             "its CUDA kernels are counted by stand-ins; on CUDA they run)")
    add_render_pixels_option(parser)
    add_backbone_start_options(parser)
    parser.add_argument("--steps", type=positive_int, default=1,
                        help="counted steps (after a warm-up)")
    parser.add_argument("--top", type=positive_int, default=12, help="source lines to list")
    parser.add_argument("--json", help="also write the census here (default: not written)")


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    overrides = {"image_size": tuple(args.image_size)} if args.image_size else {}
    if args.frames:
        overrides["num_frames"] = args.frames
    cfg = load_preset(args.preset, **overrides)
    trainer = Trainer(cfg, args.data, TrainOptions(
        out_dir=Path(tempfile.mkdtemp()), epochs=1, workers=0, progress=False,
        device=args.device, batch_size=args.batch_size,
        render_pixels_per_camera=args.render_pixels, backbone_weights=args.backbone_weights,
        backbone_from_scratch=args.backbone_from_scratch))
    dataset = trainer.dataset
    batches = [collate([dataset[(i * args.batch_size + j) % len(dataset)]
                        for j in range(args.batch_size)]) for i in range(args.steps + 1)]
    start = time.perf_counter()
    if args.renderer == "gsplat" and not args.cuda_paths:
        trainer.criterion.renderer = training_renderer("gsplat", trainer.device)
    census = census_of_steps(trainer, batches, args.cuda_paths, args.renderer)
    seconds = time.perf_counter() - start
    where = "CUDA paths forced" if args.cuda_paths else str(trainer.device)
    print(f"odg profile train: {cfg.name} {cfg.image_size[0]}x{cfg.image_size[1]}, batch "
          f"{args.batch_size}, renderer {args.renderer}, {where}, {args.steps} counted step(s) "
          f"({seconds:.1f} s with the warm-up, under the census)\n")
    print(census.report(args.top))
    gpu = None
    if trainer.device.type == "cuda":
        gpu = cuda_profile(trainer, batches[-1])
        print("\n" + gpu.pop("table"))
    if args.json:
        Path(args.json).write_text(json.dumps({"device": str(trainer.device), "gpu": gpu,
            "preset": cfg.name, "image_size": list(cfg.image_size), "cuda_paths": args.cuda_paths,
            "batch_size": args.batch_size, "ops_per_step": census.per_step(census.ops),
            "syncs_per_step": census.per_step(census.syncs),
            "renderer": args.renderer, "waits_by_kind": census.waits_by_kind(),
            "by_phase": {phase: {"ops": census.per_step(census.ops, phase),
                                 "syncs": census.per_step(census.syncs, phase)}
                         for phase in PHASES + ("other",)},
            "syncs_by_line": census.by_line(census.syncs, args.top),
            "ops_by_line": census.by_line(census.ops, args.top)}, indent=1))
    return 0


def cuda_profile(trainer, batch) -> dict:
    """Kernel time against wall time of one step on the GPU (a GPU-bound step has them close):
    the numbers, the busiest kernels, and ``table``, the text to print."""
    from torch.profiler import ProfilerActivity, profile
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        start = time.perf_counter()
        trainer.train_step(batch)
        torch.cuda.synchronize()
        wall = time.perf_counter() - start
    averages = prof.key_averages()
    kernel = sum(e.self_device_time_total for e in averages) / 1e6
    table = averages.table(sort_by="self_cuda_time_total", row_limit=10)
    busiest = sorted(averages, key=lambda e: -e.self_device_time_total)[:10]
    return {"wall_s": round(wall, 4), "kernel_s": round(kernel, 4),
            "busy": round(kernel / wall, 3),
            "top_kernels": [{"name": e.key, "calls": e.count,
                             "seconds": round(e.self_device_time_total / 1e6, 5)}
                            for e in busiest],
            "table": f"one step on the GPU: {wall:.3f} s wall, {kernel:.3f} s of kernels "
                     f"({100 * kernel / wall:.0f}% busy under the profiler)\n{table}"}
