"""``odg bench --preset NAME --device cpu|cuda [--frames K] [--iters N] [--json]``."""
from __future__ import annotations

import json

import torch

from ..benchmark import bench_online_step
from ..config import load_preset


def add_arguments(parser):
    parser.add_argument("--preset", default="odg_t")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--frames", type=int, default=None,
                        help="history frames K incl. the current one (default: the preset's)")
    parser.add_argument("--iters", type=int, default=5, help="timed iterations (median)")
    parser.add_argument("--json", action="store_true")


def run(args) -> int:
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("odg bench: --device cuda but CUDA is not available here")
    result = bench_online_step(load_preset(args.preset), args.device, args.frames, args.iters,
                               progress=not args.json)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    lat = result["latency_ms"]
    print(f"{result['preset']} on {result['device']} ({result['threads']} threads), "
          f"{result['frames']} frames, input {result['input']}: median of {result['iters']}")
    for stage in ("backbone", "decoder", "postprocess", "total"):
        print(f"  {stage:<12} {lat[stage]:9.1f} ms")
    print(f"  FPS          {result['fps']:9.2f}")
    return 0
