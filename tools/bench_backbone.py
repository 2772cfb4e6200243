"""The node step's backbone against a plain forward of the same network, on CUDA.

"Ours" is the backbone as ``OnlineStep`` runs it: BatchNorm folded into the convolutions,
weights and activations channels-last, in the step's precision (bf16: weights stored in
bf16). The references are the same ResNet with the same weights as a plain module: BatchNorm
in eval mode, fp32 weights under autocast (bf16), on NCHW input, and on channels-last input
with channels-last weights. Each runs eagerly and replayed as a CUDA graph (the node's
``graphs`` mode), on the preset's cameras at its input size; times are CUDA-event medians.

    python -m tools.bench_backbone [--preset odg_t] [--precision bf16] [--iters 50] [--json OUT]

The target: ours within 1.2x of the fastest reference in each execution mode.
"""
from __future__ import annotations

import argparse
import copy
import statistics
import sys

import torch

from odg_ros.model_config import load_preset
from odg_ros.network.backbone import ResNet, folded_for_inference
from odg_ros.network.precision import half_dtype
from tools.gpu_tool import write_json


def timed(function, x: torch.Tensor, iters: int, warmup: int, graph: bool) -> float:
    """Median milliseconds of ``function(x)``, eager or replayed as a CUDA graph."""
    with torch.inference_mode():
        if graph:
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(2):
                    function(x)
            torch.cuda.current_stream().wait_stream(side)
            captured = torch.cuda.CUDAGraph()
            with torch.cuda.graph(captured):
                function(x)
            run = captured.replay
        else:
            def run():
                function(x)
        times = []
        for i in range(warmup + iters):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            run()
            end.record()
            end.synchronize()
            if i >= warmup:
                times.append(start.elapsed_time(end))
    return statistics.median(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="odg_t")
    parser.add_argument("--precision", default="bf16", choices=("fp32", "bf16", "fp16"))
    parser.add_argument("--iters", type=int, default=50)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--json", help="also write the times here")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("bench_backbone: needs a CUDA device", file=sys.stderr)
        return 2
    torch.backends.cudnn.benchmark = True            # as the node and odg bench set it
    cfg = load_preset(args.preset)
    torch.manual_seed(0)
    plain = ResNet(cfg.backbone).cuda().eval()
    half = half_dtype(args.precision)
    ours = folded_for_inference(plain)
    if half is not None:
        ours = ours.to(half)
    H, W = cfg.image_size
    images = torch.randn(cfg.num_cams, 3, H, W, device="cuda")
    ours_input = images.contiguous(memory_format=torch.channels_last)
    if half is not None:
        ours_input = ours_input.to(half)

    plain_channels_last = copy.deepcopy(plain).to(memory_format=torch.channels_last)

    def reference(module):
        def forward(x):
            with torch.autocast("cuda", dtype=half or torch.float32, enabled=half is not None):
                return module(x)
        return forward

    inputs = {"ours": (ours, ours_input), "reference NCHW": (reference(plain), images),
              "reference channels-last": (reference(plain_channels_last),
                                          images.contiguous(memory_format=torch.channels_last))}
    result = {"preset": cfg.name, "precision": args.precision, "input": [cfg.num_cams, 3, H, W],
              "device": torch.cuda.get_device_name(), "ms": {}}
    for mode in ("eager", "graph"):
        times = {name: timed(function, x, args.iters, args.warmup, mode == "graph")
                 for name, (function, x) in inputs.items()}
        best = min(v for k, v in times.items() if k != "ours")
        result["ms"][mode] = {k: round(v, 3) for k, v in times.items()}
        result["ms"][mode]["ours / fastest reference"] = round(times["ours"] / best, 3)
        print(f"{mode}: " + ", ".join(f"{k} {v:.3f}" for k, v in result["ms"][mode].items()))
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
